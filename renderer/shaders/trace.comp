#version 460
// Ray-query path: the passes of passes.glsl in a compute shader (GL_EXT_ray_query).
#extension GL_EXT_ray_query : require
#extension GL_GOOGLE_include_directive : require

layout(local_size_x = 8, local_size_y = 8) in;

layout(set = 0, binding = 0) uniform accelerationStructureEXT tlas;

#include "common.glsl"

bool trace_closest(vec3 o, vec3 d, float tmin, float tmax,
                   out uint inst, out uint prim, out float t, out mat4x3 o2w) {
    rayQueryEXT rq;
    rayQueryInitializeEXT(rq, tlas, gl_RayFlagsOpaqueEXT, 0xff, o, tmin, d, tmax);
    while (rayQueryProceedEXT(rq)) {
    }
    if (rayQueryGetIntersectionTypeEXT(rq, true) == gl_RayQueryCommittedIntersectionNoneEXT) {
        inst = MISS;
        prim = MISS;
        t = -1.0;
        o2w = mat4x3(1.0);
        return false;
    }
    inst = rayQueryGetIntersectionInstanceCustomIndexEXT(rq, true);
    prim = rayQueryGetIntersectionPrimitiveIndexEXT(rq, true) +
           primitive_base(uint(rayQueryGetIntersectionInstanceIdEXT(rq, true)));
    t = rayQueryGetIntersectionTEXT(rq, true);
    o2w = rayQueryGetIntersectionObjectToWorldEXT(rq, true);
    return true;
}

bool trace_occluded(vec3 o, vec3 d, float tmin, float tmax) {
    rayQueryEXT rq;
    rayQueryInitializeEXT(rq, tlas, gl_RayFlagsTerminateOnFirstHitEXT | gl_RayFlagsOpaqueEXT, 0xff,
                          o, tmin, d, tmax);
    while (rayQueryProceedEXT(rq)) {
    }
    return rayQueryGetIntersectionTypeEXT(rq, true) != gl_RayQueryCommittedIntersectionNoneEXT;
}

#include "passes.glsl"

void main() {
    run_pass(gl_GlobalInvocationID.xy);
}

#version 460
// Ray-query renderer: a primary ray and one hard shadow ray toward the sun per pixel.
// Outputs packed RGBA8 colour and a hit record (customIndex, primitive, shadowed, t).
#extension GL_EXT_ray_query : require
#extension GL_GOOGLE_include_directive : require

layout(local_size_x = 8, local_size_y = 8) in;

layout(set = 0, binding = 0) uniform accelerationStructureEXT tlas;
layout(set = 0, binding = 1, std430) writeonly buffer ColorOut { uint color[]; };
layout(set = 0, binding = 2, std430) writeonly buffer HitOut { uvec4 hits[]; };

#include "common.glsl"

layout(set = 0, binding = 3, std430) readonly buffer Instances { InstanceData inst[]; };

void main() {
    uvec2 px = gl_GlobalInvocationID.xy;
    if (px.x >= pc.size.x || px.y >= pc.size.y) {
        return;
    }
    uint idx = px.y * pc.size.x + px.x;
    vec3 origin = pc.origin.xyz;
    vec3 dir = primary_dir(px);

    rayQueryEXT rq;
    rayQueryInitializeEXT(rq, tlas, gl_RayFlagsOpaqueEXT, 0xff, origin, 0.0, dir, 1e30);
    while (rayQueryProceedEXT(rq)) {
    }
    if (rayQueryGetIntersectionTypeEXT(rq, true) == gl_RayQueryCommittedIntersectionNoneEXT) {
        color[idx] = pack_rgba8(sky(dir));
        hits[idx] = uvec4(MISS, MISS, 0u, floatBitsToUint(-1.0));
        return;
    }
    uint custom = rayQueryGetIntersectionInstanceCustomIndexEXT(rq, true);
    uint prim = rayQueryGetIntersectionPrimitiveIndexEXT(rq, true);
    float t = rayQueryGetIntersectionTEXT(rq, true);
    mat4x3 o2w = rayQueryGetIntersectionObjectToWorldEXT(rq, true);
    InstanceData d = inst[custom];
    vec3 n = hit_normal(d, prim, o2w, dir);
    vec3 pos = origin + dir * t + n * 1e-3;

    uint shadowed = 0u;
    if (dot(n, pc.sun.xyz) > 0.0) {
        rayQueryEXT sq;
        rayQueryInitializeEXT(sq, tlas, gl_RayFlagsTerminateOnFirstHitEXT | gl_RayFlagsOpaqueEXT, 0xff,
                              pos, 1e-4, pc.sun.xyz, 1e30);
        while (rayQueryProceedEXT(sq)) {
        }
        shadowed = rayQueryGetIntersectionTypeEXT(sq, true) != gl_RayQueryCommittedIntersectionNoneEXT ? 1u : 0u;
    } else {
        shadowed = 1u;
    }
    color[idx] = pack_rgba8(shade(d.base_color.rgb, n, shadowed == 1u ? 0.0 : 1.0));
    hits[idx] = uvec4(custom, prim, shadowed, floatBitsToUint(t));
}

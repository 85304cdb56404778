#version 460
// Closest hit of the ray-tracing-pipeline path: report the hit like a committed ray query.
#extension GL_EXT_ray_tracing : require
#extension GL_GOOGLE_include_directive : require

#include "payload.glsl"

layout(location = 0) rayPayloadInEXT HitPayload payload;

void main() {
    payload.instance = gl_InstanceCustomIndexEXT;
    payload.primitive = gl_PrimitiveID;
    payload.record = gl_InstanceID;
    payload.t = gl_HitTEXT;
    payload.o2w = gl_ObjectToWorldEXT;
}

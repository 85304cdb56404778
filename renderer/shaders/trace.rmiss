#version 460
// Miss of the ray-tracing-pipeline path.
#extension GL_EXT_ray_tracing : require
#extension GL_GOOGLE_include_directive : require

#include "payload.glsl"

layout(location = 0) rayPayloadInEXT HitPayload payload;

void main() {
    payload.instance = MISS;
    payload.primitive = MISS;
    payload.t = -1.0;
}

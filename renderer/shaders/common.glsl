// Shared by the ray-query (compute) and ray-tracing-pipeline paths: camera rays, per-instance
// data through customIndex, hit normals, shading. Keep in sync with renderer/src/camera.rs
// (the CPU reference caster generates the same primary rays).

#extension GL_EXT_buffer_reference2 : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require

struct InstanceData {
    uint64_t vertices;   // tightly packed vec3 positions (object space), or 0
    uint64_t indices;    // uint triangle list, or 0
    vec4 base_color;     // linear RGB, a unused
};

layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Floats { float v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Uints { uint v[]; };

layout(push_constant) uniform Push {
    vec4 origin;   // xyz camera position, w = tan(fov_y / 2)
    vec4 right;    // xyz unit right, w = aspect (width / height)
    vec4 up;       // xyz unit up
    vec4 forward;  // xyz unit forward
    vec4 sun;      // xyz unit direction toward the sun
    uvec4 size;    // width, height, flags, frame
} pc;

const uint MISS = 0xffffffffu;

vec3 primary_dir(uvec2 px) {
    vec2 ndc = (vec2(px) + 0.5) / vec2(pc.size.xy) * 2.0 - 1.0;
    ndc.y = -ndc.y;
    float t = pc.origin.w;
    return normalize(pc.forward.xyz + pc.right.xyz * (ndc.x * t * pc.right.w) + pc.up.xyz * (ndc.y * t));
}

vec3 object_vertex(InstanceData d, uint primitive, uint corner) {
    uint i = Uints(d.indices).v[3u * primitive + corner];
    Floats f = Floats(d.vertices);
    return vec3(f.v[3u * i], f.v[3u * i + 1u], f.v[3u * i + 2u]);
}

// World-space face normal of the hit triangle, facing against `dir`.
vec3 hit_normal(InstanceData d, uint primitive, mat4x3 o2w, vec3 dir) {
    if (d.vertices == 0ul || d.indices == 0ul) {
        return -dir;
    }
    vec3 p0 = o2w * vec4(object_vertex(d, primitive, 0u), 1.0);
    vec3 p1 = o2w * vec4(object_vertex(d, primitive, 1u), 1.0);
    vec3 p2 = o2w * vec4(object_vertex(d, primitive, 2u), 1.0);
    vec3 n = cross(p1 - p0, p2 - p0);
    float len = length(n);
    n = len > 0.0 ? n / len : -dir;
    return dot(n, dir) > 0.0 ? -n : n;
}

vec3 sky(vec3 dir) {
    float h = clamp(dir.y * 0.5 + 0.5, 0.0, 1.0);
    return mix(vec3(0.75, 0.8, 0.9), vec3(0.35, 0.55, 0.9), h);
}

vec3 shade(vec3 base, vec3 n, float lit) {
    float ndl = max(dot(n, pc.sun.xyz), 0.0);
    float ambient = 0.18 + 0.12 * (n.y * 0.5 + 0.5);
    return base * (ambient + 0.9 * ndl * lit);
}

uint pack_rgba8(vec3 c) {
    uvec3 u = uvec3(clamp(sqrt(max(c, vec3(0.0))), 0.0, 1.0) * 255.0 + 0.5);
    return u.r | (u.g << 8) | (u.b << 16) | (255u << 24);
}

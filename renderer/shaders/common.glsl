// Shared by the ray-query (compute) and ray-tracing-pipeline paths: push constants, camera rays,
// per-instance data through customIndex, hit normals, sampling, shading. Keep in sync with
// renderer/src/camera.rs (the CPU reference caster generates the same primary rays) and with
// `Push` in renderer/src/renderer.rs.

#extension GL_EXT_buffer_reference2 : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require

#include "payload.glsl"

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
    vec4 up;       // xyz unit up, w = ambient-occlusion ray length
    vec4 forward;  // xyz unit forward, w = sun angular radius in radians (0: hard shadows)
    vec4 sun;      // xyz unit direction toward the sun
    uvec4 size;    // width, height, pass (0 primary, 1 shadow, 2 AO + shade), shadow samples
    uvec4 extra;   // AO samples (0: no AO), seed, primitive-base table address (lo, hi)
} pc;

// The first primitive of the hit record's part: a mesh split into several BLASes (one TLAS
// record per part) numbers each part's primitives from 0; the table (one uint per TLAS record,
// 0 for unsplit meshes; address 0: no table) turns them back into the mesh's primitive ids.
uint primitive_base(uint record) {
    uint64_t a = (uint64_t(pc.extra.w) << 32) | uint64_t(pc.extra.z);
    return a == 0ul ? 0u : Uints(a).v[record];
}

const uint PASS_PRIMARY = 0u;
const uint PASS_SHADOW = 1u;
const uint PASS_AO_SHADE = 2u;

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

// --- low-discrepancy sampling -------------------------------------------------------------
// R2 sequence (Roberts 2018), Cranley-Patterson rotated per pixel by a hash, so neighbouring
// pixels decorrelate while each pixel's N samples stay well stratified.

uint pcg_hash(uint v) {
    uint state = v * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

vec2 pixel_offset(uvec2 px, uint salt) {
    uint h = pcg_hash(px.x ^ pcg_hash(px.y ^ pcg_hash(salt ^ pc.extra.y)));
    uint h2 = pcg_hash(h);
    return vec2(float(h >> 8u), float(h2 >> 8u)) * (1.0 / 16777216.0);
}

vec2 r2(uint i, vec2 offset) {
    const vec2 alpha = vec2(0.7548776662466927, 0.5698402909980532);
    return fract(offset + float(i) * alpha);
}

void basis(vec3 n, out vec3 t, out vec3 b) {
    vec3 a = abs(n.x) > 0.9 ? vec3(0.0, 1.0, 0.0) : vec3(1.0, 0.0, 0.0);
    t = normalize(cross(a, n));
    b = cross(n, t);
}

// A direction toward a point of the sun's disk (angular radius `radius`), u in [0,1)^2.
vec3 sun_sample(vec2 u, float radius) {
    vec3 s = pc.sun.xyz;
    vec3 t, b;
    basis(s, t, b);
    float r = sqrt(u.x) * tan(radius);
    float phi = 6.283185307179586 * u.y;
    return normalize(s + (t * cos(phi) + b * sin(phi)) * r);
}

// Cosine-weighted direction around n, u in [0,1)^2.
vec3 cosine_sample(vec3 n, vec2 u) {
    vec3 t, b;
    basis(n, t, b);
    float r = sqrt(u.x);
    float phi = 6.283185307179586 * u.y;
    return normalize(t * (r * cos(phi)) + b * (r * sin(phi)) + n * sqrt(max(0.0, 1.0 - u.x)));
}

// --- shading ------------------------------------------------------------------------------

vec3 sky(vec3 dir) {
    float h = clamp(dir.y * 0.5 + 0.5, 0.0, 1.0);
    return mix(vec3(0.75, 0.8, 0.9), vec3(0.35, 0.55, 0.9), h);
}

// sun_vis: visible share of the sun disk; ao: unoccluded share of the hemisphere.
vec3 shade(vec3 base, vec3 n, float sun_vis, float ao) {
    float ndl = max(dot(n, pc.sun.xyz), 0.0);
    float ambient = (0.18 + 0.12 * (n.y * 0.5 + 0.5)) * ao;
    return base * (ambient + 0.9 * ndl * sun_vis);
}

uint pack_rgba8(vec3 c) {
    uvec3 u = uvec3(clamp(sqrt(max(c, vec3(0.0))), 0.0, 1.0) * 255.0 + 0.5);
    return u.r | (u.g << 8) | (u.b << 16) | (255u << 24);
}

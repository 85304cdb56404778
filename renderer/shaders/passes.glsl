// The render passes, shared by both paths. The including shader defines, before including this:
//   bool trace_closest(vec3 o, vec3 d, float tmin, float tmax,
//                      out uint inst, out uint prim, out float t, out mat4x3 o2w);
//   bool trace_occluded(vec3 o, vec3 d, float tmin, float tmax);   // opaque, first hit ends it
// and calls run_pass(pixel) once per pixel.
//
// Pass 0 (primary): closest hit -> hits (customIndex, primitive, -, t) and surf (normal).
// Pass 1 (shadow):  N rays toward the sun disk (1 when its radius is 0) -> light.x (visible
//                   share), light.z (rays traced), hits.z (shadow bit: visible share < 0.5).
// Pass 2 (AO+shade): M cosine-weighted rays of length `ao radius` -> light.y (unoccluded share),
//                   light.w (rays traced); then the colour.

layout(set = 0, binding = 1, std430) buffer ColorOut { uint color[]; };
layout(set = 0, binding = 2, std430) buffer HitOut { uvec4 hits[]; };
layout(set = 0, binding = 3, std430) readonly buffer Instances { InstanceData instances[]; };
layout(set = 0, binding = 4, std430) buffer SurfOut { vec4 surf[]; };
layout(set = 0, binding = 5, std430) buffer LightOut { vec4 light[]; };

// Shadow/AO origins are pulled off the surface by an absolute epsilon (see ARCHITECTURE.md).
const float SURFACE_EPS = 1e-3;
const float SECONDARY_TMIN = 1e-4;

InstanceData instance_data(uint custom) {
    if (custom < uint(instances.length())) {
        return instances[custom];
    }
    InstanceData d;
    d.vertices = 0ul;
    d.indices = 0ul;
    d.base_color = vec4(1.0, 0.0, 1.0, 1.0);
    return d;
}

vec3 surface_point(uvec2 px, uint idx) {
    vec3 dir = primary_dir(px);
    float t = uintBitsToFloat(hits[idx].w);
    return pc.origin.xyz + dir * t + surf[idx].xyz * SURFACE_EPS;
}

void pass_primary(uvec2 px, uint idx) {
    vec3 dir = primary_dir(px);
    uint inst;
    uint prim;
    float t;
    mat4x3 o2w;
    if (!trace_closest(pc.origin.xyz, dir, 0.0, 1e30, inst, prim, t, o2w)) {
        hits[idx] = uvec4(MISS, MISS, 0u, floatBitsToUint(-1.0));
        surf[idx] = vec4(0.0);
        return;
    }
    vec3 n = hit_normal(instance_data(inst), prim, o2w, dir);
    hits[idx] = uvec4(inst, prim, 0u, floatBitsToUint(t));
    surf[idx] = vec4(n, 0.0);
}

void pass_shadow(uvec2 px, uint idx) {
    if (hits[idx].x == MISS) {
        light[idx] = vec4(0.0);
        return;
    }
    vec3 n = surf[idx].xyz;
    vec3 pos = surface_point(px, idx);
    float radius = pc.forward.w;
    uint samples = radius > 0.0 ? max(pc.size.w, 1u) : 1u;
    float visible = 0.0;
    uint rays = 0u;
    if (dot(n, pc.sun.xyz) > 0.0) {
        vec2 offset = pixel_offset(px, 0x5eedu);
        for (uint i = 0u; i < samples; ++i) {
            vec3 d = radius > 0.0 ? sun_sample(r2(i, offset), radius) : pc.sun.xyz;
            if (dot(d, n) <= 0.0) {
                continue;
            }
            rays += 1u;
            if (!trace_occluded(pos, d, SECONDARY_TMIN, 1e30)) {
                visible += 1.0;
            }
        }
    }
    float vis = visible / float(samples);
    hits[idx].z = vis < 0.5 ? 1u : 0u;
    light[idx] = vec4(vis, 1.0, float(rays), 0.0);
}

void pass_ao_shade(uvec2 px, uint idx) {
    vec3 dir = primary_dir(px);
    uvec4 h = hits[idx];
    if (h.x == MISS) {
        color[idx] = pack_rgba8(sky(dir));
        return;
    }
    vec3 n = surf[idx].xyz;
    vec3 pos = surface_point(px, idx);
    uint samples = pc.extra.x;
    float ao = 1.0;
    if (samples > 0u) {
        vec2 offset = pixel_offset(px, 0xa0a0u);
        float open = 0.0;
        for (uint i = 0u; i < samples; ++i) {
            vec3 d = cosine_sample(n, r2(i, offset));
            if (!trace_occluded(pos, d, SECONDARY_TMIN, pc.up.w)) {
                open += 1.0;
            }
        }
        ao = open / float(samples);
    }
    vec4 l = light[idx];
    light[idx] = vec4(l.x, ao, l.z, float(samples));
    color[idx] = pack_rgba8(shade(instance_data(h.x).base_color.rgb, n, l.x, ao));
}

void run_pass(uvec2 px) {
    if (px.x >= pc.size.x || px.y >= pc.size.y) {
        return;
    }
    uint idx = px.y * pc.size.x + px.x;
    uint pass = pc.size.z;
    if (pass == PASS_PRIMARY) {
        pass_primary(px, idx);
    } else if (pass == PASS_SHADOW) {
        pass_shadow(px, idx);
    } else {
        pass_ao_shade(px, idx);
    }
}

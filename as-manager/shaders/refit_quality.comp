// Refit quality of one skinned BLAS, on the GPU: the metric of as-manager/src/quality.rs over
// the mesh's triangle order (fixed at build time: the index buffer's order), in partials.
//
// Triangles are cut into leaves of 4 and nodes of 8 leaves (32 triangles: one workgroup per
// node, looping over nodes when there are more than workgroups). Each workgroup writes one
// partial of 8 floats: [summed leaf + node box areas, node-boxes min xyz, max xyz, unused].
// The host sums the areas, merges the boxes into the root and divides by the root's area.
#version 460
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require

layout(local_size_x = 32) in;

layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Words {
    uint w[];
};
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer Partials {
    float v[];
};

layout(push_constant) uniform Push {
    uint64_t vertices;   // address of position 0
    uint64_t indices;    // address of index 0
    uint64_t partials;   // 8 floats per workgroup
    uint stride;         // bytes between positions
    uint format;         // 0: f32x3, 1: f16x4, 2: snorm16x4
    uint index_type;     // 0: u16, 1: u32
    uint triangles;
} pc;

const float BIG = 1e30;

// `addr` is a multiple of 4.
uint read32(uint64_t addr) {
    return Words(addr).w[0];
}

// `addr` is a multiple of 2: read the aligned word holding it (the engine's buffers are
// readable in whole 4-byte words, see `DeviceVertices`).
uint read16(uint64_t addr) {
    uint w = Words(addr & ~uint64_t(3)).w[0];
    return (addr & uint64_t(2)) != 0 ? (w >> 16) : (w & 0xffffu);
}

uint index_at(uint i) {
    if (pc.index_type == 0) {
        return read16(pc.indices + uint64_t(i) * 2);
    }
    return read32(pc.indices + uint64_t(i) * 4);
}

vec3 position(uint v) {
    uint64_t a = pc.vertices + uint64_t(v) * uint64_t(pc.stride);
    if (pc.format == 0) {
        return vec3(uintBitsToFloat(read32(a)), uintBitsToFloat(read32(a + 4)),
                    uintBitsToFloat(read32(a + 8)));
    }
    uint x = read16(a);
    uint y = read16(a + 2);
    uint z = read16(a + 4);
    if (pc.format == 1) {
        return vec3(unpackHalf2x16(x).x, unpackHalf2x16(y).x, unpackHalf2x16(z).x);
    }
    return vec3(unpackSnorm2x16(x).x, unpackSnorm2x16(y).x, unpackSnorm2x16(z).x);
}

float area(vec3 lo, vec3 hi) {
    vec3 d = max(hi - lo, vec3(0.0));
    return 2.0 * (d.x * d.y + d.y * d.z + d.z * d.x);
}

shared vec3 s_min[32];
shared vec3 s_max[32];

void main() {
    uint t = gl_LocalInvocationID.x;
    uint nodes = (pc.triangles + 31) / 32;
    float sum = 0.0;
    vec3 root_min = vec3(BIG);
    vec3 root_max = vec3(-BIG);
    for (uint node = gl_WorkGroupID.x; node < nodes; node += gl_NumWorkGroups.x) {
        uint tri = node * 32 + t;
        vec3 lo = vec3(BIG);
        vec3 hi = vec3(-BIG);
        if (tri < pc.triangles) {
            for (uint k = 0; k < 3; k++) {
                vec3 p = position(index_at(3 * tri + k));
                lo = min(lo, p);
                hi = max(hi, p);
            }
        }
        s_min[t] = lo;
        s_max[t] = hi;
        barrier();
        if (t == 0) {
            vec3 n_min = vec3(BIG);
            vec3 n_max = vec3(-BIG);
            for (uint leaf = 0; leaf < 8; leaf++) {
                if (node * 32 + leaf * 4 >= pc.triangles) {
                    break;
                }
                vec3 l_min = vec3(BIG);
                vec3 l_max = vec3(-BIG);
                for (uint k = 0; k < 4; k++) {
                    l_min = min(l_min, s_min[leaf * 4 + k]);
                    l_max = max(l_max, s_max[leaf * 4 + k]);
                }
                sum += area(l_min, l_max);
                n_min = min(n_min, l_min);
                n_max = max(n_max, l_max);
            }
            sum += area(n_min, n_max);
            root_min = min(root_min, n_min);
            root_max = max(root_max, n_max);
        }
        barrier();
    }
    if (t == 0) {
        Partials out_ = Partials(pc.partials + uint64_t(gl_WorkGroupID.x) * 32);
        out_.v[0] = sum;
        out_.v[1] = root_min.x;
        out_.v[2] = root_min.y;
        out_.v[3] = root_min.z;
        out_.v[4] = root_max.x;
        out_.v[5] = root_max.y;
        out_.v[6] = root_max.z;
        out_.v[7] = 0.0;
    }
}

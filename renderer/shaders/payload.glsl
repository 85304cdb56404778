// The closest-hit payload of the ray-tracing-pipeline path (rgen/rmiss/rchit), and the miss marker
// both paths write into hit buffers.

const uint MISS = 0xffffffffu;

struct HitPayload {
    uint instance;   // customIndex, or MISS
    uint primitive;  // part-relative (see primitive_base in common.glsl)
    uint record;     // index of the hit record in the TLAS
    float t;
    mat4x3 o2w;      // object-to-world of the hit instance
};

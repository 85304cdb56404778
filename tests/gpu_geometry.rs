//! GPU-resident geometry on lavapipe, validation and synchronization validation on, frames in
//! flight kept (a `FrameLoop` of two or three, the backend engine-recorded into it, nothing
//! waits before the images are read back):
//! - static meshes given by the device addresses of "engine" buffers (f32, f16 and snorm16
//!   positions with a non-tight stride, u16 and u32 indices) render what the same geometry
//!   renders as CPU slices;
//! - a skinned mesh deformed every frame by the engine's compute pass (a skinning shader
//!   compiled here with glslc) refits from the engine's buffer with no CPU upload of its
//!   positions, and renders what the CPU-posed path renders, frame by frame;
//! - scrambling its vertices on the GPU degrades the refit: the GPU quality figure crosses the
//!   rebuild bound and the manager rebuilds; an undeformed one never rebuilds.

mod common;

use std::sync::Arc;

use glam::{Affine3A, Quat, Vec3};
use rtstream::as_manager::backend::vulkan::{
    BindingKind, Bound, BufferDesc, ComputePipeline, FrameCmd, FrameLoop, GpuBuffer, MemoryKind,
    Pass, VulkanBackend, VulkanBackendDesc, VulkanContext, BUILD_INPUT_USAGE,
};
use rtstream::as_manager::{
    AsError, AsManager, Config, DeviceGeometry, DeviceIndices, DeviceVertices, FrameInput,
    GeometryData, IndexType, InstanceDesc, InstanceId, LodDesc, LodGeometry, MeshDesc, MeshKind,
    VertexFormat, Viewpoint,
};
use rtstream::renderer::{Camera, Frame, RenderDesc, Renderer};

const W: u32 = 64;
const H: u32 = 48;

/// A bumpy 12x12-quad grid, 3 m wide, whose coordinates are multiples of 1/8 (exact in f16).
fn bumpy_grid() -> GeometryData {
    let n = 12u32;
    let mut positions = Vec::new();
    for z in 0..=n {
        for x in 0..=n {
            let y = ((x * 3 + z * 5) % 4) as f32 * 0.125;
            positions.push([x as f32 * 0.25 - 1.5, y, z as f32 * 0.25 - 1.5]);
        }
    }
    let w = n + 1;
    let mut indices = Vec::new();
    for z in 0..n {
        for x in 0..n {
            let a = z * w + x;
            indices.extend([a, a + 1, a + w, a + 1, a + w + 1, a + w]);
        }
    }
    GeometryData { positions, indices }
}

/// f32 -> f16 bits for values exact in f16 (normal or zero), as an engine's asset pipeline
/// would have stored them.
fn f16_bits(v: f32) -> u16 {
    if v == 0.0 {
        return 0;
    }
    let b = v.to_bits();
    let sign = ((b >> 16) & 0x8000) as u16;
    let exp = ((b >> 23) & 0xff) as i32 - 127 + 15;
    let mant = b & 0x7f_ffff;
    assert!(
        (1..31).contains(&exp) && mant & 0x1fff == 0,
        "{v} is not exact in f16"
    );
    sign | ((exp as u16) << 10) | (mant >> 13) as u16
}

fn snorm16(v: f32) -> i16 {
    (v.clamp(-1.0, 1.0) * 32767.0).round() as i16
}

/// What the GPU reads back for a snorm16 component (Vulkan's conversion).
fn from_snorm16(i: i16) -> f32 {
    (f32::from(i) / 32767.0).max(-1.0)
}

/// The engine's own buffers: written once by the host (its asset upload) or by its compute
/// passes, read by rtstream by device address.
struct EngineBuffers {
    ctx: Arc<VulkanContext>,
    buffers: Vec<GpuBuffer>,
}

impl EngineBuffers {
    fn new(ctx: &Arc<VulkanContext>) -> Self {
        Self {
            ctx: ctx.clone(),
            buffers: Vec::new(),
        }
    }

    /// A buffer holding `bytes`, with the usage the contract asks for; returns its address.
    fn upload(&mut self, name: &'static str, bytes: &[u8]) -> u64 {
        let mut b = self
            .ctx
            .create_buffer(&BufferDesc {
                name,
                size: (bytes.len() as u64).next_multiple_of(4),
                usage: BUILD_INPUT_USAGE,
                memory: MemoryKind::Upload,
            })
            .unwrap();
        b.write(0, bytes);
        let a = b.address;
        self.buffers.push(b);
        a
    }

    /// A device-local buffer the engine's compute pass writes; returns its index.
    fn device_local(&mut self, name: &'static str, size: u64) -> usize {
        let b = self
            .ctx
            .create_buffer(&BufferDesc {
                name,
                size,
                usage: BUILD_INPUT_USAGE,
                memory: MemoryKind::DeviceLocal,
            })
            .unwrap();
        self.buffers.push(b);
        self.buffers.len() - 1
    }
}

impl Drop for EngineBuffers {
    fn drop(&mut self) {
        // The frames that used them completed (`wait_all` before the drop).
        for b in self.buffers.drain(..) {
            self.ctx.destroy_buffer(b);
        }
    }
}

/// Positions in `format` with `stride` bytes apart (the rest of each stride is filled with
/// 0xAB, which nothing may read).
fn encode_positions(p: &[[f32; 3]], format: VertexFormat, stride: usize) -> Vec<u8> {
    let mut out = vec![0xABu8; p.len() * stride];
    for (i, v) in p.iter().enumerate() {
        let at = &mut out[i * stride..];
        match format {
            VertexFormat::F32x3 => {
                for k in 0..3 {
                    at[4 * k..4 * k + 4].copy_from_slice(&v[k].to_le_bytes());
                }
            }
            VertexFormat::F16x4 => {
                for k in 0..3 {
                    at[2 * k..2 * k + 2].copy_from_slice(&f16_bits(v[k]).to_le_bytes());
                }
                at[6..8].copy_from_slice(&0u16.to_le_bytes());
            }
            VertexFormat::Snorm16x4 => {
                for k in 0..3 {
                    at[2 * k..2 * k + 2].copy_from_slice(&snorm16(v[k]).to_le_bytes());
                }
                at[6..8].copy_from_slice(&0i16.to_le_bytes());
            }
        }
    }
    out
}

fn encode_indices(ix: &[u32], t: IndexType) -> Vec<u8> {
    match t {
        IndexType::U32 => bytemuck::cast_slice(ix).to_vec(),
        IndexType::U16 => ix.iter().flat_map(|&i| (i as u16).to_le_bytes()).collect(),
    }
}

fn config() -> Config {
    let mut c = common::lavapipe_config(100.0, 120.0);
    c.residency.min_resident_frames = 0;
    c
}

fn manager(ctx: &Arc<VulkanContext>, in_flight: u32) -> AsManager<VulkanBackend> {
    common::manager(ctx, VulkanBackendDesc::engine_recorded(in_flight), config())
}

const EYE: Vec3 = Vec3::new(0.3, 2.5, -3.0);

fn render_desc() -> RenderDesc {
    RenderDesc::new(
        W,
        H,
        Camera::look_at(EYE, Vec3::new(0.0, 0.0, 0.0), 50f32.to_radians()),
    )
}

/// What a run saw.
struct Ran {
    /// The images, in frame order.
    images: Vec<Frame>,
    /// The worst refit-quality ratio any frame reported.
    worst: f32,
    /// Rebuilds the manager decided, over all frames.
    rebuilds: u32,
}

/// Runs `frames` frames with `in_flight` frames in flight: each frame the engine records its own
/// work (`engine`, before rtstream's: its skinning pass, its pose calls), the manager updates,
/// the backend's work and the renderer's passes are recorded into the same command buffer and
/// submitted; nothing waits except `FrameLoop::begin` for the frame `in_flight` back. Returns
/// the images in frame order, read back once each frame completed.
fn run(
    ctx: &Arc<VulkanContext>,
    m: &mut AsManager<VulkanBackend>,
    frames: u64,
    in_flight: u32,
    mut engine: impl FnMut(&mut AsManager<VulkanBackend>, &FrameCmd, u64),
) -> Ran {
    let mut fl = FrameLoop::new(ctx, in_flight).unwrap();
    let mut renderer = Renderer::new(ctx.clone()).unwrap();
    let mut images = Vec::new();
    let (mut worst, mut rebuilds) = (0.0f32, 0);
    let cams = [Viewpoint::new(EYE, (Vec3::ZERO - EYE).normalize())];
    for f in 0..frames {
        let cmd = fl.begin(f).unwrap();
        if let Some(done) = cmd.completed() {
            m.backend_mut().frame_done(done);
            while let Some(img) = renderer.take(images.len() as u64, Some(done)).unwrap() {
                images.push(img);
            }
        }
        engine(m, &cmd, f);
        let out = m
            .update(FrameInput {
                frame: f,
                cameras: &cams,
            })
            .unwrap();
        worst = worst.max(out.stats.worst_refit_quality);
        rebuilds += out.stats.rebuilds;
        let handle = out.tlas;
        let tlas = m.backend().resolve_tlas(handle).unwrap();
        m.backend_mut().record(&cmd).unwrap();
        renderer.record(&cmd, tlas, &[], &render_desc()).unwrap();
        fl.submit(cmd).unwrap();
    }
    fl.wait_all().unwrap();
    m.backend_mut().frame_done(frames - 1);
    while let Some(img) = renderer
        .take(images.len() as u64, Some(frames - 1))
        .unwrap()
    {
        images.push(img);
    }
    assert_eq!(images.len() as u64, frames, "every frame reads back");
    Ran {
        images,
        worst,
        rebuilds,
    }
}

fn static_mesh(geometry: LodGeometry, radius: f32) -> MeshDesc {
    MeshDesc::new(
        "grid",
        MeshKind::Static,
        radius,
        vec![LodDesc {
            geometry,
            geometric_error: 0.0,
        }],
    )
}

/// Pixels whose primary hit (instance, triangle) differs, and the largest relative difference
/// of hit distance among the others.
fn compare(a: &Frame, b: &Frame) -> (usize, f32) {
    let mut differ = 0;
    let mut worst = 0.0f32;
    for (x, y) in a.hits.iter().zip(&b.hits) {
        if x.instance != y.instance || x.primitive != y.primitive {
            differ += 1;
        } else if x.is_hit() {
            let (tx, ty) = (f32::from_bits(x.t_bits), f32::from_bits(y.t_bits));
            worst = worst.max((tx - ty).abs() / ty.max(1e-6));
        }
    }
    (differ, worst)
}

#[test]
fn static_meshes_from_device_addresses_render_like_cpu_slices() {
    let ctx = common::context();
    let grid = bumpy_grid();
    let at = Affine3A::from_translation(Vec3::new(0.0, 0.0, 0.0));

    // The easy path: CPU slices.
    let mut m = manager(&ctx, 2);
    let mesh = m
        .register_mesh(static_mesh(LodGeometry::Data(Arc::new(grid.clone())), 3.0))
        .unwrap();
    m.add_instance(InstanceDesc::new(mesh, at)).unwrap();
    let cpu = run(&ctx, &mut m, 3, 2, |_, _, _| {}).images;
    let cpu_counters = m.backend().counters();
    assert!(cpu_counters.input_upload_bytes > 0);
    drop(m);
    let hits = cpu[2].hit_fraction();
    assert!(hits > 0.2, "the grid fills the view: {hits}");

    // The engine's buffers: every format with a non-tight stride, both index types.
    let cases = [
        (VertexFormat::F32x3, 16, IndexType::U32),
        (VertexFormat::F32x3, 20, IndexType::U16),
        (VertexFormat::F16x4, 12, IndexType::U16),
        (VertexFormat::F16x4, 8, IndexType::U32),
        (VertexFormat::Snorm16x4, 16, IndexType::U16),
        (VertexFormat::Snorm16x4, 10, IndexType::U32),
    ];
    for (format, stride, index_type) in cases {
        let mut engine = EngineBuffers::new(&ctx);
        // snorm16: positions in [-1, 1] mesh space, the instance transform dequantises
        // (scale 2 here); the CPU reference is the dequantised mesh under the same transform.
        let snorm = format == VertexFormat::Snorm16x4;
        let scale = if snorm { 2.0 } else { 1.0 };
        let stored: Vec<[f32; 3]> = grid
            .positions
            .iter()
            .map(|p| p.map(|c| c / scale))
            .collect();
        let vaddr = engine.upload(
            "engine positions",
            &encode_positions(&stored, format, stride),
        );
        let iaddr = engine.upload("engine indices", &encode_indices(&grid.indices, index_type));
        let device = DeviceGeometry {
            vertices: DeviceVertices {
                address: vaddr,
                stride: stride as u64,
                format,
                count: stored.len() as u32,
            },
            indices: DeviceIndices {
                address: iaddr,
                index_type,
            },
            triangle_count: (grid.indices.len() / 3) as u32,
        };
        let transform = Affine3A::from_scale_rotation_translation(
            Vec3::splat(scale),
            Quat::IDENTITY,
            Vec3::ZERO,
        );
        let mut m = manager(&ctx, 2);
        let mesh = m
            .register_mesh(static_mesh(LodGeometry::Device(device), 3.0 / scale))
            .unwrap();
        m.add_instance(InstanceDesc::new(mesh, transform)).unwrap();
        let images = run(&ctx, &mut m, 3, 2, |_, _, _| {}).images;
        let c = m.backend().counters();
        assert_eq!(c.input_upload_bytes, 0, "{format:?}: nothing uploaded");
        assert_eq!(c.device_geometry_builds, 1, "{format:?}: {c:?}");
        drop(m);
        let reference = if snorm {
            // The CPU slices of what the GPU dequantises.
            let deq: Vec<[f32; 3]> = stored
                .iter()
                .map(|p| p.map(|c| from_snorm16(snorm16(c))))
                .collect();
            let mut m = manager(&ctx, 2);
            let mesh = m
                .register_mesh(static_mesh(
                    LodGeometry::Data(Arc::new(GeometryData {
                        positions: deq,
                        indices: grid.indices.clone(),
                    })),
                    1.5,
                ))
                .unwrap();
            m.add_instance(InstanceDesc::new(mesh, transform)).unwrap();
            run(&ctx, &mut m, 3, 2, |_, _, _| {}).images
        } else {
            cpu.clone()
        };
        for (f, (img, r)) in images.iter().zip(&reference).enumerate() {
            let (differ, worst) = compare(img, r);
            eprintln!("{format:?} stride {stride} {index_type:?} frame {f}: {differ} pixels differ, worst distance {worst:e}");
            assert_eq!(differ, 0, "{format:?}/{index_type:?} frame {f}");
            assert!(
                worst <= 1e-5,
                "{format:?}/{index_type:?} frame {f}: {worst}"
            );
        }
        if !snorm {
            // f32 and f16 (exact here) hold the very same triangles: the same image.
            assert_eq!(images[2].hits, cpu[2].hits, "{format:?}/{index_type:?}");
        } else {
            // Quantisation: within 1/32767 of the f32 mesh.
            let (differ, worst) = compare(&images[2], &cpu[2]);
            assert!(differ <= (W * H / 100) as usize, "snorm vs f32: {differ}");
            assert!(worst < 1e-3, "snorm vs f32: {worst}");
        }
        drop(engine);
    }
    // Bad addresses are typed errors.
    let m = manager(&ctx, 2);
    let bad = DeviceGeometry {
        vertices: DeviceVertices {
            address: 0x1002,
            stride: 12,
            format: VertexFormat::F32x3,
            count: 3,
        },
        indices: DeviceIndices {
            address: 0x2000,
            index_type: IndexType::U32,
        },
        triangle_count: 1,
    };
    let err = m
        .register_mesh(static_mesh(LodGeometry::Device(bad), 1.0))
        .unwrap_err();
    assert!(matches!(err, AsError::InvalidMesh { .. }), "{err}");
}

/// The engine's skinning pass: reads the rest pose (f32x3, tight), writes the pose (f32x3,
/// stride 16) for `frame`: y = x * s with s = ((frame % 5) - 2) / 8 (one multiplication, exact
/// the same on the CPU), or, with `scramble`, vertex i takes vertex (i * 37) % n's position.
const SKINNING: &str = r#"#version 460
layout(local_size_x = 64) in;
layout(set = 0, binding = 0, std430) readonly buffer Rest { float rest[]; };
layout(set = 0, binding = 1, std430) writeonly buffer Pose { float pose[]; };
layout(push_constant) uniform P { uint count; float s; uint scramble; } pc;
void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= pc.count) return;
    uint src = pc.scramble != 0 ? (i * 37u) % pc.count : i;
    float x = rest[3 * src];
    float z = rest[3 * src + 2];
    float y = pc.scramble != 0 ? rest[3 * src + 1] : x * pc.s;
    pose[4 * i] = x;
    pose[4 * i + 1] = y;
    pose[4 * i + 2] = z;
    pose[4 * i + 3] = 0.0;
}
"#;

fn skinning_pipeline(ctx: &VulkanContext) -> ComputePipeline {
    // Compiled once per test process, through glslc's stdin and stdout (no files that tests
    // running in parallel could share).
    static SPIRV: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    let code = SPIRV.get_or_init(|| {
        use std::io::Write;
        use std::process::{Command, Stdio};
        let glslc = std::env::var("GLSLC").unwrap_or_else(|_| "glslc".into());
        let mut child = Command::new(&glslc)
            .args([
                "-fshader-stage=comp",
                "--target-env=vulkan1.2",
                "-O",
                "-",
                "-o",
                "-",
            ])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("glslc ({glslc}): {e}; run scripts/setup.sh"));
        child
            .stdin
            .take()
            .expect("piped stdin")
            .write_all(SKINNING.as_bytes())
            .unwrap();
        let out = child.wait_with_output().unwrap();
        assert!(out.status.success(), "glslc failed on the skinning shader");
        out.stdout
    });
    ComputePipeline::new(
        ctx,
        "engine skinning",
        code,
        &[BindingKind::StorageBuffer, BindingKind::StorageBuffer],
        12,
    )
    .unwrap()
}

fn wave_scale(frame: u64) -> f32 {
    ((frame % 5) as f32 - 2.0) * 0.125
}

fn skinned_mesh(geometry: LodGeometry) -> MeshDesc {
    MeshDesc::new(
        "cloth",
        MeshKind::Skinned,
        3.0,
        vec![LodDesc {
            geometry,
            geometric_error: 0.0,
        }],
    )
}

/// A skinned instance posed by the engine's GPU skinning every frame, with `scramble(frame)`.
struct GpuSkinned {
    m: AsManager<VulkanBackend>,
    id: InstanceId,
    engine: EngineBuffers,
    pose: usize,
    rest: usize,
    /// The engine's skinning pipeline (`None` once destroyed).
    skin: Option<ComputePipeline>,
    count: u32,
    ctx: Arc<VulkanContext>,
}

impl Drop for GpuSkinned {
    fn drop(&mut self) {
        // Every frame that used the pipeline completed (`run` waits for all before returning).
        if let Some(skin) = self.skin.take() {
            skin.destroy(&self.ctx);
        }
    }
}

fn gpu_skinned(ctx: &Arc<VulkanContext>, grid: &GeometryData, in_flight: u32) -> GpuSkinned {
    let mut engine = EngineBuffers::new(ctx);
    let rest = engine.buffers.len();
    engine.upload("engine rest pose", bytemuck::cast_slice(&grid.positions));
    let iaddr = engine.upload(
        "engine indices",
        &encode_indices(&grid.indices, IndexType::U16),
    );
    let count = grid.positions.len() as u32;
    let pose = engine.device_local("engine skinned pose", u64::from(count) * 16);
    let vertices = DeviceVertices {
        address: engine.buffers[pose].address,
        stride: 16,
        format: VertexFormat::F32x3,
        count,
    };
    let m = manager(ctx, in_flight);
    // The LOD's topology from the engine's index buffer; its rest positions are the pose
    // buffer too (the pose is set before the first build).
    let mesh = m
        .register_mesh(skinned_mesh(LodGeometry::Device(DeviceGeometry {
            vertices,
            indices: DeviceIndices {
                address: iaddr,
                index_type: IndexType::U16,
            },
            triangle_count: (grid.indices.len() / 3) as u32,
        })))
        .unwrap();
    let id = m
        .add_instance(InstanceDesc::new(mesh, Affine3A::IDENTITY))
        .unwrap();
    GpuSkinned {
        m,
        id,
        engine,
        pose,
        rest,
        skin: Some(skinning_pipeline(ctx)),
        count,
        ctx: ctx.clone(),
    }
}

/// Runs the GPU-skinned instance; `scramble(frame)` picks the deformation.
fn run_gpu_skinned(
    ctx: &Arc<VulkanContext>,
    s: &mut GpuSkinned,
    frames: u64,
    in_flight: u32,
    scramble: impl Fn(u64) -> bool,
) -> Ran {
    let GpuSkinned {
        m,
        id,
        engine,
        pose,
        rest,
        skin,
        count,
        ..
    } = s;
    let skin = skin.as_mut().expect("live pipeline");
    let address = engine.buffers[*pose].address;
    run(ctx, m, frames, in_flight, |m, cmd, f| {
        let mut push = Vec::new();
        push.extend_from_slice(&count.to_le_bytes());
        push.extend_from_slice(&wave_scale(f).to_le_bytes());
        push.extend_from_slice(&u32::from(scramble(f)).to_le_bytes());
        skin.record(
            ctx,
            cmd,
            &[
                Bound::Buffer(&engine.buffers[*rest]),
                Bound::Buffer(&engine.buffers[*pose]),
            ],
            &[Pass {
                push: &push,
                grid: [count.div_ceil(64), 1, 1],
            }],
            None,
        )
        .unwrap();
        m.set_skinned_pose_device(
            *id,
            DeviceVertices {
                address,
                stride: 16,
                format: VertexFormat::F32x3,
                count: *count,
            },
        )
        .unwrap();
    })
}

#[test]
fn a_mesh_skinned_on_the_gpu_refits_without_upload_and_renders_like_cpu_poses() {
    const FRAMES: u64 = 8;
    let ctx = common::context();
    let grid = bumpy_grid();
    for in_flight in [2, 3] {
        let mut s = gpu_skinned(&ctx, &grid, in_flight);
        let gpu = run_gpu_skinned(&ctx, &mut s, FRAMES, in_flight, |_| false).images;
        let c = s.m.backend().counters();
        eprintln!("GPU-skinned, {in_flight} in flight: {c:?}");
        assert_eq!(
            c.pose_upload_bytes, 0,
            "no CPU copy of the positions: {c:?}"
        );
        assert_eq!(c.input_upload_bytes, 0, "{c:?}");
        assert!(c.refits >= FRAMES - 2, "refitted every frame: {c:?}");
        assert_eq!(c.rebuilds, 0, "a smooth wave never degrades: {c:?}");
        assert!(
            c.gpu_quality_reports > 0,
            "quality measured on the GPU: {c:?}"
        );

        // The CPU-posed path with the same positions.
        let mut m = manager(&ctx, in_flight);
        let mesh = m
            .register_mesh(skinned_mesh(LodGeometry::Data(Arc::new(grid.clone()))))
            .unwrap();
        let id = m
            .add_instance(InstanceDesc::new(mesh, Affine3A::IDENTITY))
            .unwrap();
        let cpu = run(&ctx, &mut m, FRAMES, in_flight, |m, _, f| {
            let sc = wave_scale(f);
            let pose: Vec<[f32; 3]> = grid
                .positions
                .iter()
                .map(|p| [p[0], p[0] * sc, p[2]])
                .collect();
            m.set_skinned_pose(id, Arc::new(pose)).unwrap();
        })
        .images;
        let cc = m.backend().counters();
        assert!(cc.pose_upload_bytes > 0, "{cc:?}");
        assert_eq!(cc.refits, c.refits);
        drop(m);
        for (f, (a, b)) in gpu.iter().zip(&cpu).enumerate() {
            // Frame 0 builds the cloth; a frame's builds show from the next one.
            assert!(
                f == 0 || a.hit_fraction() > 0.2,
                "frame {f} shows the cloth: {}",
                a.hit_fraction()
            );
            assert_eq!(a.hits, b.hits, "{in_flight} in flight, frame {f}");
        }
        // The poses differ frame to frame: the refits took effect.
        assert_ne!(gpu[1].hits, gpu[2].hits);
        drop(s);
    }
}

#[test]
fn scrambled_gpu_poses_cross_the_quality_bound_and_rebuild_an_undeformed_one_never() {
    const FRAMES: u64 = 12;
    let ctx = common::context();
    let grid = bumpy_grid();
    let bound = config().build.rebuild_quality_bound;

    // Undeformed: the rest pose every frame (refitted each frame, never degraded).
    let mut calm = gpu_skinned(&ctx, &grid, 2);
    let ran = run_gpu_skinned(&ctx, &mut calm, FRAMES, 2, |_| false);
    let c = calm.m.backend().counters();
    eprintln!("undeformed: {c:?}, worst ratio {}", ran.worst);
    assert!(
        c.gpu_quality_reports >= FRAMES - 4,
        "measured every refit: {c:?}"
    );
    assert!(ran.worst < bound, "{}", ran.worst);
    assert_eq!((c.rebuilds, ran.rebuilds), (0, 0), "{c:?}");
    drop(calm);

    // Scrambled from frame 3 on: far-apart vertices swap, the refit's boxes balloon.
    let mut wild = gpu_skinned(&ctx, &grid, 2);
    let ran = run_gpu_skinned(&ctx, &mut wild, FRAMES, 2, |f| f >= 3);
    let c = wild.m.backend().counters();
    let worst = ran.worst;
    eprintln!("scrambled: {c:?}, worst ratio {worst} (bound {bound})");
    assert!(worst > bound, "the GPU figure crossed the bound: {worst}");
    assert!(
        c.rebuilds >= 1 && ran.rebuilds >= 1,
        "the manager rebuilt it: {c:?}"
    );
    // Once rebuilt for the scrambled shape, the same shape does not degrade again.
    assert!(c.rebuilds <= 2, "{c:?}");
}

//! GPU measurements of acceleration-structure work (benchmarks and the cost-model fit), as safe
//! functions over owned objects: every timing comes from GPU timestamps around the commands.

use ash::vk;
use rtstream_stats::Samples;

use crate::backend::vulkan::device::accel::{
    align_up, AccelStruct, BlasBuildInput, TlasBuildInput, TriangleGeometry, BUILD_INPUT_USAGE,
};
use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::device::geometry::GpuGeometry;
use crate::backend::vulkan::device::query::{QueryKind, QueryPool};
use crate::backend::vulkan::error::VkResult;
use crate::record::{TlasInstance, INSTANCE_FORCE_OPAQUE};

/// Runs `record` between two timestamps in one submit and returns the GPU milliseconds.
fn timed(
    ctx: &VulkanContext,
    ts: &QueryPool,
    name: &str,
    record: impl FnOnce(vk::CommandBuffer),
) -> VkResult<f64> {
    ts.reset(ctx);
    ctx.submit_and_wait(name, |_, cmd| {
        // SAFETY: cmd is recording; the pool was reset above and holds 2 queries.
        unsafe { ts.cmd_timestamp(ctx, cmd, 0) };
        record(cmd);
        // SAFETY: as above.
        unsafe { ts.cmd_timestamp(ctx, cmd, 1) };
    })?;
    let t = ts.read(ctx, 0, 2)?;
    Ok(ts.ticks_to_ms(t[1].saturating_sub(t[0])))
}

/// Builds one BLAS over `geom` now (one submit, waited) and returns it.
pub fn build_blas_now(
    ctx: &VulkanContext,
    geom: &GpuGeometry,
    flags: vk::BuildAccelerationStructureFlagsKHR,
    name: &str,
) -> VkResult<AccelStruct> {
    let geoms = [std::slice::from_ref(&geom.geometry)];
    let batch = ctx.plan_blas_batch(&geoms, flags, |_| name.to_owned())?;
    // Freed unless the build succeeds.
    let batch = scopeguard::guard(batch, |b| b.destroy(ctx));
    ctx.failpoint("build_blas_now.scratch")?;
    let (scratch, base) = ctx.create_scratch("build_blas_now scratch", batch.scratch.total())?;
    let builds = batch.inputs(&geoms, flags, base);
    let r = ctx.submit_and_wait(name, |_, cmd| {
        // SAFETY: geometry, BLAS and scratch live until the wait returns.
        unsafe { ctx.cmd_build_blases(cmd, &builds) }
    });
    ctx.destroy_buffer(scratch);
    r?;
    let mut batch = scopeguard::ScopeGuard::into_inner(batch);
    Ok(batch.accels.pop().expect("one BLAS planned"))
}

/// Builds one BLAS per entry of `geoms` (entries may repeat the same geometry) with `flags` —
/// all in one vkCmdBuildAccelerationStructuresKHR (`batched`) or one call each — `reps` times
/// after a warm-up. Returns (median GPU ms, bytes of the first BLAS).
pub fn time_blas_builds(
    ctx: &VulkanContext,
    geoms: &[&GpuGeometry],
    flags: vk::BuildAccelerationStructureFlagsKHR,
    batched: bool,
    reps: usize,
) -> VkResult<(f64, u64)> {
    let lists: Vec<&[TriangleGeometry]> = geoms
        .iter()
        .map(|g| std::slice::from_ref(&g.geometry))
        .collect();
    let batch = ctx.plan_blas_batch(&lists, flags, |i| format!("bench blas {i}"))?;
    let first_bytes = batch.sizes.first().map_or(0, |s| s.storage);
    let ts = match QueryPool::new(ctx, QueryKind::Timestamp, 2, "time_blas_builds") {
        Ok(ts) => ts,
        Err(e) => {
            batch.destroy(ctx);
            return Err(e);
        }
    };
    let mut times = Vec::with_capacity(reps);
    let mut result = Ok(());
    match ctx.create_scratch("time_blas_builds scratch", batch.scratch.total()) {
        Ok((scratch, base)) => {
            let builds = batch.inputs(&lists, flags, base);
            for rep in 0..=reps {
                let ms = timed(ctx, &ts, "time_blas_builds", |cmd| {
                    // SAFETY: everything referenced lives until the wait; scratch ranges are
                    // disjoint, so the unbatched calls need no barrier between them.
                    unsafe {
                        if batched {
                            ctx.cmd_build_blases(cmd, &builds);
                        } else {
                            for b in &builds {
                                ctx.cmd_build_blases(cmd, std::slice::from_ref(b));
                            }
                        }
                    }
                });
                match ms {
                    Ok(ms) if rep > 0 => times.push(ms),
                    Ok(_) => {}
                    Err(e) => {
                        result = Err(e);
                        break;
                    }
                }
            }
            ctx.destroy_buffer(scratch);
        }
        Err(e) => result = Err(e),
    }
    batch.destroy(ctx);
    ts.destroy(ctx);
    result.map(|()| (Samples::new(times).median(), first_bytes))
}

/// What recording BLAS builds costs the host (the driver's work in
/// vkCmdBuildAccelerationStructuresKHR, which the manager pays inside `update`): median wall
/// milliseconds of the call, apart from the GPU's time. See [`time_build_recording`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RecordingCost {
    /// The first call in a fresh command buffer, building every BLAS.
    pub first_call_ms: f64,
    /// A second call in the same command buffer, building as many other BLASes.
    pub second_call_ms: f64,
    /// With `ALLOW_UPDATE` in the flags: a call updating the first call's BLASes in place.
    pub update_ms: Option<f64>,
}

/// The host's cost of recording builds of one BLAS per entry of `geoms` with `flags`: each of
/// `reps` repetitions (after a warm-up) records two calls into one command buffer, each
/// building its own set of BLASes (no hazard between them), times each call on the host, and
/// submits; with `ALLOW_UPDATE`, a further submit records an update of the first set in place.
pub fn time_build_recording(
    ctx: &VulkanContext,
    geoms: &[&GpuGeometry],
    flags: vk::BuildAccelerationStructureFlagsKHR,
    reps: usize,
) -> VkResult<RecordingCost> {
    let lists: Vec<&[TriangleGeometry]> = geoms
        .iter()
        .map(|g| std::slice::from_ref(&g.geometry))
        .collect();
    let first = ctx.plan_blas_batch(&lists, flags, |i| format!("recording blas a{i}"))?;
    let first = scopeguard::guard(first, |b| b.destroy(ctx));
    let second = ctx.plan_blas_batch(&lists, flags, |i| format!("recording blas b{i}"))?;
    let second = scopeguard::guard(second, |b| b.destroy(ctx));
    // The updates reuse the first set's scratch: room for the larger of build and update.
    let room = |b: &crate::backend::vulkan::device::accel::BlasBatch| {
        b.sizes
            .iter()
            .map(|s| s.build_scratch.max(s.update_scratch))
            .max()
            .unwrap_or(0)
    };
    let per = room(&first).max(room(&second));
    let align = ctx.info().min_scratch_alignment.max(1);
    let slot = per.div_ceil(align) * align;
    let n = geoms.len() as u64;
    let (scratch, base) = ctx.create_scratch("time_build_recording scratch", 2 * n * slot)?;
    let scratch = scopeguard::guard(scratch, |b| ctx.destroy_buffer(b));
    let inputs = |batch: &crate::backend::vulkan::device::accel::BlasBatch, at: u64| {
        lists
            .iter()
            .zip(&batch.accels)
            .enumerate()
            .map(|(i, (g, a))| BlasBuildInput {
                geometries: g,
                flags,
                dst: a.raw,
                update_from: None,
                scratch_address: at + i as u64 * slot,
            })
            .collect::<Vec<_>>()
    };
    let builds_a = inputs(&first, base);
    let builds_b = inputs(&second, base + n * slot);
    let updates: Vec<BlasBuildInput<'_>> = builds_a
        .iter()
        .map(|b| BlasBuildInput {
            update_from: Some(b.dst),
            ..*b
        })
        .collect();
    let can_update = flags.contains(vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE);
    let (mut one, mut two, mut upd) = (Vec::new(), Vec::new(), Vec::new());
    for rep in 0..=reps {
        let (mut a, mut b) = (0.0, 0.0);
        ctx.submit_and_wait("time_build_recording", |_, cmd| {
            let t = std::time::Instant::now();
            // SAFETY: everything referenced lives until the wait; the two calls build
            // disjoint BLASes from disjoint scratch ranges.
            unsafe { ctx.cmd_build_blases(cmd, &builds_a) };
            a = t.elapsed().as_secs_f64() * 1e3;
            let t = std::time::Instant::now();
            // SAFETY: as above.
            unsafe { ctx.cmd_build_blases(cmd, &builds_b) };
            b = t.elapsed().as_secs_f64() * 1e3;
        })?;
        if can_update {
            let mut u = 0.0;
            ctx.submit_and_wait("time_build_recording update", |_, cmd| {
                let t = std::time::Instant::now();
                // SAFETY: the first set was built with ALLOW_UPDATE by the submit waited for
                // above; each updates in place from its own scratch range.
                unsafe { ctx.cmd_build_blases(cmd, &updates) };
                u = t.elapsed().as_secs_f64() * 1e3;
            })?;
            if rep > 0 {
                upd.push(u);
            }
        }
        if rep > 0 {
            one.push(a);
            two.push(b);
        }
    }
    drop(updates);
    drop(builds_a);
    drop(builds_b);
    ctx.destroy_buffer(scopeguard::ScopeGuard::into_inner(scratch));
    scopeguard::ScopeGuard::into_inner(first).destroy(ctx);
    scopeguard::ScopeGuard::into_inner(second).destroy(ctx);
    Ok(RecordingCost {
        first_call_ms: Samples::new(one).median(),
        second_call_ms: Samples::new(two).median(),
        update_ms: can_update.then(|| Samples::new(upd).median()),
    })
}

/// Result of [`compaction_sizes`].
#[derive(Debug, Clone, PartialEq)]
pub struct CompactionResult {
    /// (original bytes, compacted bytes) per geometry, in order.
    pub sizes: Vec<(u64, u64)>,
    /// GPU ms of all the compacting copies (one submit).
    pub copy_gpu_ms: f64,
}

/// Builds a FAST_TRACE + ALLOW_COMPACTION BLAS per geometry (one batched build), queries the
/// compacted sizes, compacts every one into a new structure and times the copies.
pub fn compaction_sizes(ctx: &VulkanContext, geoms: &[GpuGeometry]) -> VkResult<CompactionResult> {
    let flags = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE
        | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION;
    let pool = QueryPool::new(
        ctx,
        QueryKind::CompactedSize,
        geoms.len() as u32,
        "compacted sizes",
    )?;
    let ts = QueryPool::new(ctx, QueryKind::Timestamp, 2, "compaction timestamps")?;
    let mut accels = Vec::new();
    let mut dsts = Vec::new();
    let mut scratch = None;
    let result = (|| {
        let lists: Vec<&[TriangleGeometry]> = geoms
            .iter()
            .map(|g| std::slice::from_ref(&g.geometry))
            .collect();
        let batch = ctx.plan_blas_batch(&lists, flags, |_| "compaction source".into())?;
        let (buf, base) = match ctx.create_scratch("compaction scratch", batch.scratch.total()) {
            Ok(s) => s,
            Err(e) => {
                batch.destroy(ctx);
                return Err(e);
            }
        };
        scratch = Some(buf);
        let builds = batch.inputs(&lists, flags, base);
        accels = batch.accels;
        let raws: Vec<_> = accels.iter().map(|a: &AccelStruct| a.raw).collect();
        ctx.submit_and_wait("compaction build", |_, cmd| {
            // SAFETY: everything referenced lives until the wait; the barrier orders the builds
            // before the size queries; the query pool was reset at creation.
            unsafe {
                ctx.cmd_build_blases(cmd, &builds);
                ctx.cmd_accel_barrier(cmd);
                pool.cmd_compacted_sizes(ctx, cmd, &raws, 0);
            }
        })?;
        let compacted = pool.read(ctx, 0, geoms.len() as u32)?;
        for &c in &compacted {
            dsts.push(ctx.create_accel(
                vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
                c.max(256),
                "compacted",
            )?);
        }
        let copy_gpu_ms = timed(ctx, &ts, "compaction copy", |cmd| {
            for (a, d) in accels.iter().zip(&dsts) {
                // SAFETY: sources were built and queried by the completed submit above; each
                // destination is at least the queried compacted size.
                unsafe { ctx.cmd_compact(cmd, a.raw, d.raw) };
            }
        })?;
        let sizes = accels
            .iter()
            .zip(&compacted)
            .map(|(a, &c)| (a.size, c))
            .collect();
        Ok(CompactionResult { sizes, copy_gpu_ms })
    })();
    for a in accels.into_iter().chain(dsts) {
        ctx.destroy_accel(a);
    }
    if let Some(s) = scratch {
        ctx.destroy_buffer(s);
    }
    pool.destroy(ctx);
    ts.destroy(ctx);
    result
}

/// A deforming (skinned) mesh: builds it once with FAST_BUILD + ALLOW_UPDATE, then for each of
/// `reps` new poses (from `pose(rep)`) times a refit (UPDATE, src = dst) and a full rebuild.
/// Returns (median refit GPU ms, median rebuild GPU ms).
pub fn time_refit_vs_rebuild(
    ctx: &VulkanContext,
    geom: &mut GpuGeometry,
    pose: &mut dyn FnMut(usize) -> Vec<[f32; 3]>,
    reps: usize,
) -> VkResult<(f64, f64)> {
    let flags = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD
        | vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE;
    let s = ctx.blas_sizes(std::slice::from_ref(&geom.geometry), flags);
    let blas = build_blas_now(ctx, geom, flags, "refit bench")?;
    let ts = QueryPool::new(ctx, QueryKind::Timestamp, 2, "refit timestamps")?;
    let (scratch, base) =
        ctx.create_scratch("refit scratch", s.build_scratch.max(s.update_scratch))?;
    let mut refits = Vec::new();
    let mut rebuilds = Vec::new();
    let mut result = Ok(());
    'outer: for rep in 0..=reps {
        for update in [true, false] {
            geom.write_positions(&pose(rep * 2 + usize::from(update)));
            let b = BlasBuildInput {
                geometries: std::slice::from_ref(&geom.geometry),
                flags,
                dst: blas.raw,
                update_from: update.then_some(blas.raw),
                scratch_address: base,
            };
            let ms = timed(ctx, &ts, "refit bench", |cmd| {
                // SAFETY: BLAS, geometry and scratch live until the wait; src == dst is allowed
                // for updates; the BLAS was built with ALLOW_UPDATE.
                unsafe { ctx.cmd_build_blases(cmd, std::slice::from_ref(&b)) }
            });
            match ms {
                Ok(ms) if rep > 0 => {
                    if update {
                        refits.push(ms)
                    } else {
                        rebuilds.push(ms)
                    }
                }
                Ok(_) => {}
                Err(e) => {
                    result = Err(e);
                    break 'outer;
                }
            }
        }
    }
    ctx.destroy_accel(blas);
    ctx.destroy_buffer(scratch);
    ts.destroy(ctx);
    result.map(|()| {
        (
            Samples::new(refits).median(),
            Samples::new(rebuilds).median(),
        )
    })
}

/// Builds a TLAS over one record per transform (all referencing `blas`) with `flags`, `reps`
/// times after a warm-up. Returns (median GPU ms, TLAS bytes).
pub fn time_tlas_build(
    ctx: &VulkanContext,
    blas: &AccelStruct,
    transforms: &[[f32; 16]],
    flags: vk::BuildAccelerationStructureFlagsKHR,
    reps: usize,
) -> VkResult<(f64, u64)> {
    let n = transforms.len() as u32;
    let records = instance_records(blas, transforms);
    let s = ctx.tlas_sizes(n, flags);
    let ibuf = ctx.create_buffer_with_data(
        "tlas bench instances",
        BUILD_INPUT_USAGE,
        bytemuck::cast_slice(&records),
    )?;
    let ts = QueryPool::new(ctx, QueryKind::Timestamp, 2, "tlas timestamps")?;
    let mut tlas = None;
    let mut scratch = None;
    let result = (|| {
        let t = create_tlas(ctx, s.storage, "bench tlas")?;
        let raw = t.raw;
        tlas = Some(t);
        let (buf, base) = ctx.create_scratch("bench tlas scratch", s.build_scratch)?;
        scratch = Some(buf);
        let mut times = Vec::new();
        for rep in 0..=reps {
            let ms = timed(ctx, &ts, "tlas bench", |cmd| {
                // SAFETY: the BLAS is built (the caller's contract), the instance buffer, TLAS and
                // scratch live until the wait.
                unsafe { ctx.cmd_build_tlas(cmd, raw, None, flags, ibuf.address, n, base) }
            })?;
            if rep > 0 {
                times.push(ms);
            }
        }
        Ok((Samples::new(times).median(), s.storage))
    })();
    if let Some(t) = tlas {
        ctx.destroy_accel(t);
    }
    if let Some(b) = scratch {
        ctx.destroy_buffer(b);
    }
    ctx.destroy_buffer(ibuf);
    ts.destroy(ctx);
    result
}

/// GPU medians of a frame's TLAS build beside a batch of BLAS builds the TLAS does not
/// reference, recorded several ways ([`time_tlas_beside_builds`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BesideBuilds {
    /// The BLAS batch alone.
    pub builds_ms: f64,
    /// The TLAS alone.
    pub tlas_ms: f64,
    /// The batch, a barrier, then the TLAS (the order a TLAS that uses the new BLASes needs).
    pub serial_ms: f64,
    /// The batch, then the TLAS in another call, no barrier between them.
    pub no_barrier_ms: f64,
    /// The batch and the TLAS in one vkCmdBuildAccelerationStructuresKHR.
    pub one_call_ms: f64,
    /// The TLAS, a timestamp, then the batch (no barrier): the whole span, and the span to
    /// the middle timestamp (whether a timestamp between them keeps them apart).
    pub tlas_first_ms: f64,
    /// The middle timestamp of `tlas_first_ms`.
    pub tlas_first_mid_ms: f64,
    /// The batch, a timestamp, then the TLAS (no barrier): the whole span and to the middle.
    pub builds_first_ms: f64,
    /// The middle timestamp of `builds_first_ms`.
    pub builds_first_mid_ms: f64,
}

/// What a frame's TLAS costs beside its BLAS builds, when the TLAS need not wait for them (its
/// records reference other BLASes): a TLAS over `transforms` (instances of `blas`, built
/// before) and one new BLAS per entry of `geoms`, timed alone and together several ways (see
/// [`BesideBuilds`]). Each of `reps` submits (after a warm-up) records every way 8 times, in
/// rotating order, with three timestamps and a barrier around each, so the GPU stays busy (its
/// clocks up) and the ways share its state. Medians.
pub fn time_tlas_beside_builds(
    ctx: &VulkanContext,
    blas: &AccelStruct,
    transforms: &[[f32; 16]],
    geoms: &[&GpuGeometry],
    blas_flags: vk::BuildAccelerationStructureFlagsKHR,
    tlas_flags: vk::BuildAccelerationStructureFlagsKHR,
    reps: usize,
) -> VkResult<BesideBuilds> {
    const WAYS: usize = 7;
    const INNER: usize = 8;
    const QUERIES: u32 = (3 * WAYS * INNER) as u32;
    let n = transforms.len() as u32;
    let records = instance_records(blas, transforms);
    let lists: Vec<&[TriangleGeometry]> = geoms
        .iter()
        .map(|g| std::slice::from_ref(&g.geometry))
        .collect();
    let batch = ctx.plan_blas_batch(&lists, blas_flags, |i| format!("beside blas {i}"))?;
    let batch = scopeguard::guard(batch, |b| b.destroy(ctx));
    let s = ctx.tlas_sizes(n, tlas_flags);
    let ibuf = ctx.create_buffer_with_data(
        "beside tlas instances",
        BUILD_INPUT_USAGE,
        bytemuck::cast_slice(&records),
    )?;
    let ibuf = scopeguard::guard(ibuf, |b| ctx.destroy_buffer(b));
    let tlas = create_tlas(ctx, s.storage, "beside tlas")?;
    let tlas = scopeguard::guard(tlas, |t| ctx.destroy_accel(t));
    let align = ctx.info().min_scratch_alignment.max(1);
    let blas_scratch = align_up(batch.scratch.total(), align);
    let (scratch, base) =
        ctx.create_scratch("beside scratch", blas_scratch + s.build_scratch.max(1))?;
    let _scratch = scopeguard::guard(scratch, |b| ctx.destroy_buffer(b));
    let ts = QueryPool::new(ctx, QueryKind::Timestamp, QUERIES, "beside timestamps")?;
    let ts = scopeguard::guard(ts, |t| t.destroy(ctx));
    let builds = batch.inputs(&lists, blas_flags, base);
    let tlas_in = TlasBuildInput {
        dst: tlas.raw,
        flags: tlas_flags,
        instances_address: ibuf.address,
        instance_count: n,
        scratch_address: base + blas_scratch,
    };
    let mut span: [Vec<f64>; WAYS] = Default::default();
    let mut mid: [Vec<f64>; WAYS] = Default::default();
    for rep in 0..=reps {
        ts.reset(ctx);
        ctx.submit_and_wait("time_tlas_beside_builds", |_, cmd| {
            for i in 0..INNER {
                for k in 0..WAYS {
                    let way = (k + i + rep) % WAYS;
                    let q = ((i * WAYS + way) * 3) as u32;
                    // SAFETY: cmd is recording; the pool was reset above and holds every
                    // index; the BLAS of the records was built before (the caller's
                    // contract), everything referenced lives until the wait, the scratch
                    // ranges are disjoint, and the TLAS references none of the batch's BLASes
                    // (which the ways without a barrier between them need); the barrier after
                    // each way orders its writes before the next way's.
                    unsafe {
                        let tlas_only =
                            |cmd| ctx.cmd_build_blases_with_tlas(cmd, &[], Some(&tlas_in));
                        ts.cmd_timestamp(ctx, cmd, q);
                        match way {
                            0 => {
                                ts.cmd_timestamp(ctx, cmd, q + 1);
                                ctx.cmd_build_blases(cmd, &builds);
                            }
                            1 => {
                                ts.cmd_timestamp(ctx, cmd, q + 1);
                                tlas_only(cmd);
                            }
                            2 => {
                                ctx.cmd_build_blases(cmd, &builds);
                                ctx.cmd_accel_barrier(cmd);
                                ts.cmd_timestamp(ctx, cmd, q + 1);
                                tlas_only(cmd);
                            }
                            3 => {
                                ts.cmd_timestamp(ctx, cmd, q + 1);
                                ctx.cmd_build_blases(cmd, &builds);
                                tlas_only(cmd);
                            }
                            4 => {
                                ts.cmd_timestamp(ctx, cmd, q + 1);
                                ctx.cmd_build_blases_with_tlas(cmd, &builds, Some(&tlas_in));
                            }
                            5 => {
                                tlas_only(cmd);
                                ts.cmd_timestamp(ctx, cmd, q + 1);
                                ctx.cmd_build_blases(cmd, &builds);
                            }
                            _ => {
                                ctx.cmd_build_blases(cmd, &builds);
                                ts.cmd_timestamp(ctx, cmd, q + 1);
                                tlas_only(cmd);
                            }
                        }
                        ts.cmd_timestamp(ctx, cmd, q + 2);
                        ctx.cmd_accel_barrier(cmd);
                    }
                }
            }
        })?;
        let t = ts.read(ctx, 0, QUERIES)?;
        if rep > 0 {
            for (q, tri) in t.chunks_exact(3).enumerate() {
                span[q % WAYS].push(ts.ticks_to_ms(tri[2].saturating_sub(tri[0])));
                mid[q % WAYS].push(ts.ticks_to_ms(tri[1].saturating_sub(tri[0])));
            }
        }
    }
    drop(builds);
    let span = span.map(|v| Samples::new(v).median());
    let mid = mid.map(|v| Samples::new(v).median());
    Ok(BesideBuilds {
        builds_ms: span[0],
        tlas_ms: span[1],
        serial_ms: span[2],
        no_barrier_ms: span[3],
        one_call_ms: span[4],
        tlas_first_ms: span[5],
        tlas_first_mid_ms: mid[5],
        builds_first_ms: span[6],
        builds_first_mid_ms: mid[6],
    })
}

/// Median GPU ms of a TLAS build and of an update in place over `transforms` (instances of
/// `blas`), both with `PREFER_FAST_TRACE | ALLOW_UPDATE`: the build from the given transforms,
/// the updates alternating between them and the same moved by half a metre (every instance
/// changes, as in a frame where everything moved). `reps` timed repetitions each, after one
/// warm-up. Returns (build ms, update ms).
pub fn time_tlas_update(
    ctx: &VulkanContext,
    blas: &AccelStruct,
    transforms: &[[f32; 16]],
    reps: usize,
) -> VkResult<(f64, f64)> {
    let flags = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE
        | vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE;
    let n = transforms.len() as u32;
    let records = |dx: f32| -> Vec<TlasInstance> {
        let moved = glam::Affine3A::from_translation(glam::Vec3::new(dx, 0.0, 0.0));
        transforms
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let at = moved * glam::Affine3A::from_mat4(glam::Mat4::from_cols_array(t));
                let ci = (i as u32) & 0xff_ffff;
                TlasInstance::new(&at, ci, 0xff, 0, INSTANCE_FORCE_OPAQUE, blas.address)
            })
            .collect()
    };
    let s = ctx.tlas_sizes(n, flags);
    let mut owned: Vec<crate::backend::vulkan::device::buffer::GpuBuffer> = Vec::new();
    let mut tlas = None;
    let ts = QueryPool::new(ctx, QueryKind::Timestamp, 2, "tlas update timestamps")?;
    let result = (|| {
        for dx in [0.0, 0.5] {
            let name = "tlas update bench instances";
            let data = records(dx);
            owned.push(ctx.create_buffer_with_data(
                name,
                BUILD_INPUT_USAGE,
                bytemuck::cast_slice(&data),
            )?);
        }
        let (a, b) = (owned[0].address, owned[1].address);
        let t = create_tlas(ctx, s.storage, "tlas update bench")?;
        let raw = t.raw;
        tlas = Some(t);
        let (buf, base) =
            ctx.create_scratch("tlas update scratch", s.build_scratch.max(s.update_scratch))?;
        owned.push(buf);
        let mut builds = Vec::new();
        for rep in 0..=reps {
            // SAFETY: the BLAS is built (the caller's contract); the instance buffers, the TLAS
            // and the scratch live until the wait inside `timed`.
            let ms = timed(ctx, &ts, "tlas update bench build", |cmd| unsafe {
                ctx.cmd_build_tlas(cmd, raw, None, flags, a, n, base)
            })?;
            if rep > 0 {
                builds.push(ms);
            }
        }
        // The last build was from `a`: updates go to `b`, back to `a`, ...
        let mut updates = Vec::new();
        for rep in 0..=reps {
            let from = if rep % 2 == 0 { b } else { a };
            // SAFETY: as above; `raw` was built with ALLOW_UPDATE from as many instances, and
            // the previous submit (a build or an update of it) completed.
            let ms = timed(ctx, &ts, "tlas update bench update", |cmd| unsafe {
                ctx.cmd_build_tlas(cmd, raw, Some(raw), flags, from, n, base)
            })?;
            if rep > 0 {
                updates.push(ms);
            }
        }
        Ok((
            Samples::new(builds).median(),
            Samples::new(updates).median(),
        ))
    })();
    if let Some(t) = tlas {
        ctx.destroy_accel(t);
    }
    for b in owned {
        ctx.destroy_buffer(b);
    }
    ts.destroy(ctx);
    result
}

/// A TLAS of `storage` bytes in a buffer of its own.
/// One opaque TLAS record of `blas` per transform (custom index: its position).
fn instance_records(blas: &AccelStruct, transforms: &[[f32; 16]]) -> Vec<TlasInstance> {
    transforms
        .iter()
        .enumerate()
        .map(|(i, t)| {
            TlasInstance::new(
                &glam::Affine3A::from_mat4(glam::Mat4::from_cols_array(t)),
                (i as u32) & 0xff_ffff,
                0xff,
                0,
                INSTANCE_FORCE_OPAQUE,
                blas.address,
            )
        })
        .collect()
}

fn create_tlas(ctx: &VulkanContext, storage: u64, name: &str) -> VkResult<AccelStruct> {
    ctx.create_accel(vk::AccelerationStructureTypeKHR::TOP_LEVEL, storage, name)
}

//! BLAS builds, refits, compaction and frees, recorded into the frame being recorded.
//!
//! The frame's builds are laid out in the frame's scratch arena with the same
//! [`ScratchLayout`] as the one-shot batches (`VulkanContext::plan_blas_batch`: the static
//! scene, the benchmarks, compaction). What stays here is what only the frame path has: sizes
//! from the backend's cache (no driver call per queued item), oversized meshes split into
//! parts, refit-target rings, and device-address inputs.

use super::gpu_quality::{vk_format, vk_index, GpuQuality, Measured, QualityInputs};
use super::*;
use crate::mesh::{DeviceVertices, IndexType, VertexFormat};

impl VulkanBackend {
    /// Splits a geometry's triangle range into parts that respect the device and size limits.
    pub(super) fn parts_of(&self, g: &GeometryRef<'_>, class: BlasClass, sizes: &BlasSizes) -> u32 {
        let max_prims = self.ctx.info().max_primitive_count.max(1);
        let by_prims = u64::from(g.triangle_count).div_ceil(max_prims);
        let biggest = sizes.as_bytes.max(sizes.build_scratch);
        let by_bytes = biggest.div_ceil(self.desc.max_part_bytes.max(1));
        // Skinned meshes are refitted as one structure: never split them.
        if class == BlasClass::Skinned {
            return 1;
        }
        by_prims
            .max(by_bytes)
            .clamp(1, u64::from(g.triangle_count.max(1))) as u32
    }

    /// Checks a build's geometry (what the GPU would read past otherwise) and returns its
    /// sizes: the caller's, but never below the backend's own for this geometry (a build
    /// given another mesh's sizes would write past its storage).
    fn checked_build(&self, b: &BlasBuild<'_>) -> BackendResult<BlasSizes> {
        let g = &b.geometry;
        let bad = |what| Err(Misuse::InvalidGeometry(what).into());
        if g.triangle_count == 0 || g.vertex_count == 0 {
            return bad("no triangles or no vertices");
        }
        if let Some(p) = g.positions.filter(|_| g.device_vertices.is_none()) {
            if p.len() < g.vertex_count as usize {
                return bad("fewer positions than vertex_count");
            }
        }
        if let Some(v) = g.device_vertices {
            v.validate().map_err(Misuse::DeviceGeometry)?;
            if v.count < g.vertex_count {
                return bad("fewer device vertices than vertex_count");
            }
        }
        if let Some(i) = g.device_indices {
            i.validate().map_err(Misuse::DeviceGeometry)?;
        }
        if let Some(idx) = g.indices.filter(|_| g.device_indices.is_none()) {
            let n = g.triangle_count as usize * 3;
            let Some(used) = idx.get(..n) else {
                return bad("fewer indices than 3 x triangle_count");
            };
            // The CPU's indices are read here anyway (copied to the GPU): one pass more.
            if used.iter().copied().max().unwrap_or(0) >= g.vertex_count {
                return bad("an index past the vertices");
            }
        }
        let own = self.blas_sizes(g, b.class);
        Ok(BlasSizes {
            as_bytes: b.sizes.as_bytes.max(own.as_bytes),
            build_scratch: b.sizes.build_scratch.max(own.build_scratch),
            update_scratch: b.sizes.update_scratch.max(own.update_scratch),
        })
    }

    pub(super) fn record_blas_builds(
        &mut self,
        builds: &[BlasBuild<'_>],
    ) -> BackendResult<Vec<BlasHandle>> {
        self.fault(FaultPoint::BuildBlases)?;
        if builds.is_empty() {
            return Ok(Vec::new());
        }
        // A frame is being recorded (the builds are recorded with its TLAS).
        self.cmd()?;
        // Geometry the GPU can build from, and room for it: nothing is allocated before.
        let sizes: Vec<BlasSizes> = builds
            .iter()
            .map(|b| self.checked_build(b))
            .collect::<BackendResult<_>>()?;
        struct Planned {
            geoms: Vec<TriangleGeometry>,
            accels: Vec<AccelStruct>,
            scratch: Vec<u64>,
            skinned: Option<SkinnedInputs>,
            inputs: Option<StaticInputs>,
            shading: (u64, u64),
            shading_plain: bool,
            /// Bytes of one index.
            index_bytes: u64,
            /// Built from the engine's positions: them, and the index address and type.
            device: Option<(DeviceVertices, u64, IndexType)>,
        }
        let mut planned: Vec<Planned> = Vec::with_capacity(builds.len());
        let align = self.ctx.info().min_scratch_alignment;
        let plan = tracing::trace_span!("plan").entered();
        let result: BackendResult<()> = (|| {
            for (b, checked) in builds.iter().zip(&sizes) {
                let g = &b.geometry;
                let device_v = g.device_vertices;
                if device_v.is_none() && g.positions.is_none() {
                    return Err(BackendError::MissingGeometry);
                }
                let parts = self.parts_of(g, b.class, checked);
                let format = device_v.map_or(VertexFormat::F32x3, |v| v.format);
                let cpu_static = b.class == BlasClass::Static
                    && device_v.is_none()
                    && g.device_indices.is_none();
                let (iaddr, itype, vaddr, stride, skinned, inputs) = if cpu_static {
                    // CPU positions and indices: one buffer holds both.
                    let (Some(pos), Some(idx)) = (g.positions, g.indices) else {
                        return Err(BackendError::MissingGeometry);
                    };
                    let s = self.upload_static_inputs(pos, idx)?;
                    let a = s.range.address;
                    let iaddr = a + StaticInputs::index_offset(s.positions_bytes);
                    (iaddr, IndexType::U32, a, 12, None, Some(s))
                } else {
                    // Indices: the engine's (read in place) or the CPU's (uploaded once).
                    let (ib, iaddr, itype) = match (g.device_indices, g.indices) {
                        (Some(d), _) => (None, d.address, d.index_type),
                        (None, Some(idx)) => {
                            let ib =
                                self.upload_input("BLAS indices", bytemuck::cast_slice(idx))?;
                            self.counters.input_upload_bytes += (idx.len() * 4) as u64;
                            let a = ib.address;
                            (Some(ib), a, IndexType::U32)
                        }
                        (None, None) => return Err(BackendError::MissingGeometry),
                    };
                    if b.class == BlasClass::Skinned {
                        let (vaddr, stride, poses) = match (device_v, g.positions) {
                            (Some(v), _) => (v.address, v.stride, Vec::new()),
                            (None, Some(pos)) => match self.pose_buffer(pos) {
                                Ok(pb) => (pb.address, 12, vec![pb]),
                                Err(e) => {
                                    self.destroy_all(ib);
                                    return Err(e);
                                }
                            },
                            (None, None) => unreachable!("checked above"),
                        };
                        let next = poses.len();
                        let skinned = SkinnedInputs {
                            indices: ib,
                            index_address: iaddr,
                            index_type: itype,
                            vertex_format: format,
                            opaque: g.opaque,
                            triangles: g.triangle_count,
                            vertices: g.vertex_count,
                            poses,
                            next,
                        };
                        (iaddr, itype, vaddr, stride, Some(skinned), None)
                    } else {
                        match (device_v, ib) {
                            // The engine's buffers: nothing to upload or keep.
                            (Some(v), None) => (iaddr, itype, v.address, v.stride, None, None),
                            (_, ib) => {
                                self.destroy_all(ib);
                                return Err(Misuse::InvalidGeometry(
                                    "static geometry mixes device and CPU inputs",
                                )
                                .into());
                            }
                        }
                    }
                };
                let p = Planned {
                    geoms: Vec::new(),
                    accels: Vec::new(),
                    scratch: Vec::new(),
                    skinned,
                    inputs,
                    shading: (vaddr, iaddr),
                    shading_plain: format == VertexFormat::F32x3
                        && stride == 12
                        && itype == IndexType::U32,
                    index_bytes: itype.size(),
                    device: device_v.map(|v| (v, iaddr, itype)),
                };
                let tris = b.geometry.triangle_count;
                let per = tris.div_ceil(parts);
                planned.push(p);
                let p = planned.last_mut().expect("just pushed");
                for k in 0..parts {
                    let first = k * per;
                    let count = per.min(tris - first);
                    if count == 0 {
                        break;
                    }
                    let g = TriangleGeometry {
                        vertex_address: vaddr,
                        vertex_format: vk_format(format),
                        index_type: vk_index(itype),
                        vertex_stride: stride,
                        max_vertex: b.geometry.vertex_count.saturating_sub(1),
                        index_address: iaddr + u64::from(first) * 3 * itype.size(),
                        triangle_count: count,
                        opaque: b.geometry.opaque,
                    };
                    let s = if parts == 1 {
                        crate::backend::vulkan::device::accel::AsSizes {
                            // One structure of the ring (`as_bytes` counts all of them).
                            storage: checked.as_bytes / self.ring_len(b.class),
                            build_scratch: checked.build_scratch,
                            update_scratch: checked.update_scratch,
                        }
                    } else {
                        self.ctx.blas_sizes(&[g], self.blas_flags(b.class))
                    };
                    let a = self.create_accel(s.storage, "BLAS")?;
                    p.geoms.push(g);
                    p.accels.push(a);
                    p.scratch
                        .push(align_up(s.build_scratch.max(s.update_scratch), align));
                }
            }
            let total: u64 = planned.iter().flat_map(|p| p.scratch.iter()).sum();
            self.ensure_scratch(total)
        })();
        drop(plan);
        if let Err(e) = result {
            // All or nothing: release what this call created (nothing was recorded yet).
            for p in planned {
                for a in p.accels {
                    self.destroy(Retired::BlasAccel(a));
                }
                for b in p.skinned.into_iter().flat_map(SkinnedInputs::buffers) {
                    self.destroy(Retired::BlasBuffer(b));
                }
                if let Some(s) = p.inputs {
                    self.destroy(Retired::BlasInput(s.range));
                }
            }
            return Err(e);
        }
        // Recorded with the frame's TLAS (`record_pending_builds`): beside it when no record
        // names these BLASes.
        for (b, p) in builds.iter().zip(&planned) {
            let flags = self.blas_flags(b.class);
            for (g, (a, sc)) in p.geoms.iter().zip(p.accels.iter().zip(&p.scratch)) {
                let scratch_address = self.scratch_alloc(*sc);
                self.pending
                    .inputs
                    .push((*g, flags, a.raw, scratch_address));
                self.pending.addresses.push(a.address);
            }
        }
        self.pending.addresses.sort_unstable();
        let tris: u64 = builds
            .iter()
            .map(|b| u64::from(b.geometry.triangle_count))
            .sum();
        let any_static = builds.iter().any(|b| b.class != BlasClass::Skinned)
            || self.pending.op == Some(CostOp::BuildStatic);
        self.pending.op = Some(if any_static {
            CostOp::BuildStatic
        } else {
            CostOp::BuildSkinned
        });
        self.pending.triangles += tris;
        self.pending.blases += builds.len() as u32;
        self.frame_build_triangles += tris;
        // Compacted-size queries for static BLASes (single-part only).
        let statics: Vec<usize> = (0..builds.len())
            .filter(|&i| builds[i].class == BlasClass::Static && planned[i].accels.len() == 1)
            .collect();
        let mut handles = Vec::with_capacity(builds.len());
        let mut query_targets = Vec::new();
        let frame = self.slots[self.current].frame;
        for (i, (b, p)) in builds.iter().zip(planned).enumerate() {
            if p.accels.len() > 1 {
                self.counters.split_meshes += 1;
                let first = p.accels[0].address;
                let iaddr = p.shading.1;
                let parts = p.accels[1..]
                    .iter()
                    .zip(&p.geoms[1..])
                    .map(|(a, g)| {
                        let first = (g.index_address - iaddr) / (3 * p.index_bytes);
                        (a.address, first as u32)
                    })
                    .collect();
                self.split_parts.insert(first, parts);
            }
            let raw0 = p.accels[0].raw;
            let measure = p.device.filter(|_| b.class == BlasClass::Skinned);
            if p.device.is_some() {
                self.counters.device_geometry_builds += 1;
            }
            let h = self.insert(BlasEntry {
                parts: p.accels,
                class: b.class,
                sizes: sizes[i],
                skinned: p.skinned,
                static_inputs: p.inputs,
                spares: Vec::new(),
                shading: p.shading,
                shading_plain: p.shading_plain,
                compacted_size: None,
                compacted: false,
                recorded: frame,
                gpu_quality: measure.map(|_| GpuQuality {
                    build_gen: 1,
                    built_metric: None,
                }),
            });
            if let Some((vertices, index_address, index_type)) = measure {
                // The reference metric of this build, measured on the GPU.
                let inputs = QualityInputs {
                    vertices,
                    index_address,
                    index_type,
                    triangles: b.geometry.triangle_count,
                };
                self.measure_quality(h, Measured::Build, inputs);
            }
            if statics.contains(&i) {
                query_targets.push((h, raw0));
            }
            handles.push(h);
            self.counters.built += 1;
        }
        self.pending.queries.extend(query_targets);
        Ok(handles)
    }

    /// Whether a TLAS over `records` (changed since the last call where `delta` says) names
    /// a BLAS built this frame: then the builds must finish before it.
    pub(super) fn records_name_pending(
        &self,
        records: &[TlasInstance],
        delta: TlasDelta<'_>,
    ) -> bool {
        let pending = &self.pending.addresses;
        if pending.is_empty() {
            return false;
        }
        let named = |r: &TlasInstance| pending.binary_search(&r.blas_address).is_ok();
        // Records before `stable` and not listed are last call's: none can name a BLAS that
        // did not exist then.
        let from = delta.stable.min(records.len());
        records[from..].iter().any(named)
            || delta
                .changed
                .iter()
                .filter_map(|&i| records.get(i as usize))
                .any(named)
    }

    /// Records the frame's pending BLAS builds and compactions (timed), then a barrier and the
    /// builds' compacted-size queries: before a TLAS that names one of them, or at the end of a
    /// frame without a TLAS.
    pub(super) fn record_pending_builds(&mut self, cmd: vk::CommandBuffer) {
        self.record_builds(cmd, true);
        self.record_compacted_size_queries(cmd);
    }

    /// Records the frame's pending BLAS builds, then its compactions, with no barrier after
    /// them, for the TLAS that follows (it names none of them) to run beside them; `timed`
    /// false leaves them out of the timestamps (the TLAS's pair, begun before them, covers
    /// them all: a timestamp between them would make the GPU finish them first,
    /// `docs/GPU.md`). Returns what the builds were (op, triangles, BLASes), or with no build
    /// what the compactions were (`CostOp::Compact`, source bytes, count).
    /// `record_compacted_size_queries` follows the TLAS.
    pub(super) fn record_builds(
        &mut self,
        cmd: vk::CommandBuffer,
        timed: bool,
    ) -> Option<(CostOp, u64, u32)> {
        let builds = self.record_pending_blas_builds(cmd, timed);
        let compactions = self.record_compactions(cmd, timed);
        self.pending.addresses.clear();
        builds.or(compactions)
    }

    /// The pending compactions, after the builds: each timed on its own (`timed`), else
    /// untimed inside the TLAS's pair. Returns (op, source bytes, count) when any.
    fn record_compactions(
        &mut self,
        cmd: vk::CommandBuffer,
        timed: bool,
    ) -> Option<(CostOp, u64, u32)> {
        let mut compactions = std::mem::take(&mut self.pending.compactions);
        if compactions.is_empty() {
            return None;
        }
        let mut bytes = 0;
        for &(src, dst, b) in &compactions {
            let t = if timed {
                self.timestamp_begin(CostOp::Compact, b, 1)
            } else {
                self.counters.compactions_beside_tlas += 1;
                None
            };
            // SAFETY: recording; the source was built in an earlier, completed frame (its
            // size query was read) and begin_frame's barrier orders it; dst is at least the
            // compacted size, and nothing this frame reads it before a barrier (a TLAS that
            // names it is recorded after one: `records_name_pending`).
            unsafe { self.ctx.cmd_compact(cmd, src, dst) };
            self.timestamp_end(t);
            bytes += b;
        }
        let n = compactions.len() as u32;
        compactions.clear();
        self.pending.compactions = compactions;
        Some((CostOp::Compact, bytes, n))
    }

    /// The pending BLAS builds (see `record_builds`).
    fn record_pending_blas_builds(
        &mut self,
        cmd: vk::CommandBuffer,
        timed: bool,
    ) -> Option<(CostOp, u64, u32)> {
        let op = self.pending.op.take()?;
        let inputs = std::mem::take(&mut self.pending.inputs);
        let raw: Vec<BlasBuildInput<'_>> = inputs
            .iter()
            .map(|(g, flags, dst, scratch_address)| BlasBuildInput {
                geometries: std::slice::from_ref(g),
                flags: *flags,
                dst: *dst,
                update_from: None,
                scratch_address: *scratch_address,
            })
            .collect();
        let (triangles, blases) = (self.pending.triangles, self.pending.blases);
        self.pending.triangles = 0;
        self.pending.blases = 0;
        let t = if timed {
            self.timestamp_begin(op, triangles, blases)
        } else {
            None
        };
        let recording = tracing::trace_span!("cmd_build").entered();
        // SAFETY: cmd is recording; inputs are the BLASes' own buffers (or the engine's,
        // which it keeps until the frame completes), retired with them after the frame
        // completes; scratch ranges are disjoint and aligned, and the frame's scratch is not
        // reused before it completes.
        unsafe { self.ctx.cmd_build_blases(cmd, &raw) };
        drop(recording);
        self.timestamp_end(t);
        Some((op, triangles, blases))
    }

    /// After the frame's builds (and the TLAS beside them): a barrier, then the compacted-size
    /// queries of its static single-part BLASes.
    pub(super) fn record_compacted_size_queries(&mut self, cmd: vk::CommandBuffer) {
        let mut queries = std::mem::take(&mut self.pending.queries);
        let s = &mut self.slots[self.current];
        let room = (COMPACT_QUERIES_PER_SLOT as usize).saturating_sub(s.compact_queries.len());
        queries.truncate(room);
        if queries.is_empty() {
            return;
        }
        let first = s.compact_queries.len() as u32;
        let raws: Vec<_> = queries.iter().map(|(_, r)| *r).collect();
        // SAFETY: recording; the barrier orders the builds before the queries, which were
        // reset in begin_frame and are written once.
        unsafe {
            self.ctx.cmd_accel_barrier(cmd);
            s.compact_pool
                .cmd_compacted_sizes(&self.ctx, cmd, &raws, first);
        }
        for (k, (h, _)) in queries.into_iter().enumerate() {
            s.compact_queries.push((h, first + k as u32));
        }
    }

    pub(super) fn record_refits(&mut self, refits: &[BlasRefit<'_>]) -> BackendResult<()> {
        self.fault(FaultPoint::RefitBlases)?;
        if refits.is_empty() {
            return Ok(());
        }
        let cmd = self.cmd()?;
        let align = self.ctx.info().min_scratch_alignment;
        /// One refit, planned before anything is recorded.
        struct Plan<'r> {
            r: &'r BlasRefit<'r>,
            index_address: u64,
            index_type: IndexType,
            tris: u32,
            verts: u32,
            src: vk::AccelerationStructureKHR,
            scratch: u64,
            /// Update (`false`) or build into the same storage.
            rebuild: bool,
            /// The pose in the engine's buffer (`None`: CPU positions, copied to the ring).
            device: Option<DeviceVertices>,
            /// The driver's sizes for inputs other than the build's (another vertex format or
            /// opacity): the BLAS's scratch sizes from then on.
            resized: Option<BlasSizes>,
        }
        let mut plan = Vec::with_capacity(refits.len());
        let mut total = 0;
        // A refit of a BLAS whose build is pending (made this frame) must follow the build.
        let mut names_pending = false;
        for (i, r) in refits.iter().enumerate() {
            if refits[..i].iter().any(|q| q.blas == r.blas) {
                return Err(Misuse::DuplicateRefit(r.blas).into());
            }
            let e = self.entry(r.blas).ok_or(Misuse::UnknownBlas(r.blas))?;
            names_pending |= self
                .pending
                .addresses
                .binary_search(&e.parts[0].address)
                .is_ok();
            let Some(sk) = &e.skinned else {
                return Err(Misuse::NotSkinned(r.blas).into());
            };
            let (count, device) = match (r.geometry.device_vertices, r.geometry.positions) {
                (Some(v), _) => {
                    v.validate().map_err(Misuse::DeviceGeometry)?;
                    (v.count, Some(v))
                }
                (None, Some(p)) => (p.len() as u32, None),
                (None, None) => return Err(BackendError::MissingGeometry),
            };
            if count != sk.vertices || r.geometry.triangle_count != sk.triangles {
                return Err(Misuse::TopologyChanged(r.blas).into());
            }
            // An update must read the format the BLAS was built from; another one rebuilds.
            let format = device.map_or(VertexFormat::F32x3, |v| v.format);
            // So must it keep the build's geometry flags (opaque).
            let changed = format != sk.vertex_format || r.geometry.opaque != sk.opaque;
            let rebuild = r.rebuild || changed;
            // Other inputs may need other sizes (the spec leaves them to the driver): the
            // rebuild must fit the BLAS's storage, and takes its scratch from the new sizes.
            let resized = changed.then(|| self.blas_sizes(&r.geometry, BlasClass::Skinned));
            if let Some(s) = resized {
                let needs = s.as_bytes / self.ring_len(BlasClass::Skinned).max(1);
                if needs > e.parts[0].size {
                    return Err(Misuse::RefitOutgrowsStorage {
                        blas: r.blas,
                        needs,
                        has: e.parts[0].size,
                    }
                    .into());
                }
            }
            let scratch = match (resized, rebuild) {
                (Some(s), _) => s.build_scratch,
                (None, true) => e.sizes.build_scratch,
                (None, false) => e.sizes.update_scratch,
            };
            total += align_up(scratch.max(1), align);
            plan.push(Plan {
                r,
                index_address: sk.index_address,
                index_type: sk.index_type,
                tris: sk.triangles,
                verts: sk.vertices,
                src: e.parts[0].raw,
                scratch,
                rebuild,
                device,
                resized,
            });
        }
        // Separate refit targets: each refit writes a structure no frame in flight traces (a
        // new one while the ring is short, else the oldest spare, current `frames_in_flight`
        // refits ago); it becomes current once recorded.
        let ring = self.ring_len(BlasClass::Skinned);
        let mut targets = Vec::with_capacity(plan.len());
        for p in &plan {
            if ring == 1 {
                targets.push(p.src);
                continue;
            }
            let key = key_of(p.r.blas);
            let (short, size) = {
                let e = self.blases.get(key).expect("checked above");
                ((e.spares.len() as u64) < ring - 1, e.parts[0].size)
            };
            if short {
                let a = self.create_accel(size, "BLAS refit target")?;
                self.by_address.insert(a.address, key);
                let e = self.blases.get_mut(key).expect("checked above");
                e.spares.insert(0, a);
            }
            targets.push(self.blases.get(key).expect("checked above").spares[0].raw);
        }
        self.ensure_scratch(total)?;
        let mut geoms = Vec::with_capacity(plan.len());
        for p in &plan {
            let (vaddr, stride, format) = match p.device {
                Some(v) => {
                    // Read in place: the shading reads the engine's buffer too.
                    let key = key_of(p.r.blas);
                    if let Some(e) = self.blases.get_mut(key) {
                        e.shading.0 = v.address;
                        e.shading_plain = v.format == VertexFormat::F32x3
                            && v.stride == 12
                            && p.index_type == IndexType::U32;
                    }
                    (v.address, v.stride, v.format)
                }
                None => {
                    let key = key_of(p.r.blas);
                    if let Some(e) = self.blases.get_mut(key) {
                        e.shading_plain = p.index_type == IndexType::U32;
                    }
                    let pos = p.r.geometry.positions.expect("checked above");
                    (self.write_pose(p.r.blas, pos)?, 12, VertexFormat::F32x3)
                }
            };
            geoms.push(TriangleGeometry {
                vertex_address: vaddr,
                vertex_format: vk_format(format),
                index_type: vk_index(p.index_type),
                vertex_stride: stride,
                max_vertex: p.verts.saturating_sub(1),
                index_address: p.index_address,
                triangle_count: p.tris,
                opaque: p.r.geometry.opaque,
            });
        }
        if names_pending {
            // The builds (and the frame's compactions) go first, behind a barrier.
            self.record_pending_builds(cmd);
        }
        // The refits write (and read) their BLASes in this frame: their frees wait for it.
        let frame = self.slots[self.current].frame;
        for p in &plan {
            if let Some(e) = self.blases.get_mut(key_of(p.r.blas)) {
                e.recorded = frame;
            }
        }
        let mut raw = Vec::with_capacity(plan.len());
        let mut tris_total = 0u64;
        let flags = self.blas_flags(BlasClass::Skinned);
        for (i, p) in plan.iter().enumerate() {
            let scratch_address = self.scratch_alloc(p.scratch.max(1));
            tris_total += u64::from(p.tris);
            raw.push(BlasBuildInput {
                geometries: std::slice::from_ref(&geoms[i]),
                flags,
                dst: targets[i],
                update_from: (!p.rebuild).then_some(p.src),
                scratch_address,
            });
            if p.rebuild {
                self.counters.rebuilds += 1;
            } else {
                self.counters.refits += 1;
            }
        }
        let t = self.timestamp_begin(CostOp::Refit, tris_total, plan.len() as u32);
        // SAFETY: recording; the barrier orders this frame's earlier builds (and previous frames'
        // traces, via begin_frame's barrier) before the updates; src == dst is allowed. The
        // engine's pose buffers were written before this frame (begin_frame's input barrier).
        unsafe {
            self.ctx.cmd_accel_barrier(cmd);
            self.ctx.cmd_build_blases(cmd, &raw);
        }
        self.timestamp_end(t);
        drop(raw);
        for p in &plan {
            let key = key_of(p.r.blas);
            let e = self.blases.get_mut(key).expect("checked above");
            if ring > 1 {
                // Recorded: the target becomes current, the structure it replaces the newest
                // spare (frames in flight may still trace it).
                let target = e.spares.remove(0);
                let old = std::mem::replace(&mut e.parts[0], target);
                e.spares.push(old);
            }
            let format = p.device.map_or(VertexFormat::F32x3, |v| v.format);
            if let Some(sk) = e.skinned.as_mut() {
                sk.vertex_format = format;
                sk.opaque = p.r.geometry.opaque;
            }
            if let Some(s) = p.resized {
                e.sizes.build_scratch = s.build_scratch;
                e.sizes.update_scratch = s.update_scratch;
            }
            let Some(vertices) = p.device else {
                // CPU poses: the manager measures quality on the CPU.
                e.gpu_quality = None;
                continue;
            };
            // Posed on the GPU: after a rebuild (or the first refit from the GPU) this pass
            // measures the new reference; after an update, the refit's quality.
            let kind = match (&mut e.gpu_quality, p.rebuild) {
                (Some(_), false) => Measured::Refit,
                (Some(q), true) => {
                    q.build_gen += 1;
                    q.built_metric = None;
                    Measured::Build
                }
                (None, _) => {
                    e.gpu_quality = Some(GpuQuality {
                        build_gen: 1,
                        built_metric: None,
                    });
                    Measured::Build
                }
            };
            let inputs = QualityInputs {
                vertices,
                index_address: p.index_address,
                index_type: p.index_type,
                triangles: p.tris,
            };
            self.measure_quality(p.r.blas, kind, inputs);
        }
        Ok(())
    }

    pub(super) fn record_compaction(&mut self, blas: BlasHandle) -> BackendResult<BlasHandle> {
        self.fault(FaultPoint::CompactBlas)?;
        // A frame is recording (the copy is recorded with its builds).
        self.cmd()?;
        let e = self.entry(blas).ok_or(Misuse::UnknownBlas(blas))?;
        if e.compacted {
            return Err(Misuse::AlreadyCompacted(blas).into());
        }
        if self
            .pending
            .addresses
            .binary_search(&e.parts[0].address)
            .is_ok()
        {
            return Err(Misuse::CompactionOfPending(blas).into());
        }
        let size = e.compacted_size.ok_or(Misuse::CompactedSizeUnknown(blas))?;
        let (src, class, sizes, shading, shading_plain) =
            (e.parts[0].raw, e.class, e.sizes, e.shading, e.shading_plain);
        let dst = self.create_accel(size.max(256), "compacted BLAS")?;
        let bytes = entry_storage_bytes(self.entry(blas));
        // The compacted copy takes over the input buffers (shading reads them).
        // The copy reads the source in this frame: its free waits for this frame.
        let frame = self.slots[self.current].frame;
        let inputs = self.blases.get_mut(key_of(blas)).and_then(|e| {
            e.recorded = frame;
            e.compacted = true;
            e.static_inputs.take()
        });
        // Recorded with the frame's builds (`record_builds`): beside the TLAS when no record
        // names the copy.
        self.pending.compactions.push((src, dst.raw, bytes));
        let at = self.pending.addresses.partition_point(|&a| a < dst.address);
        self.pending.addresses.insert(at, dst.address);
        self.counters.compactions += 1;
        let copy = self.insert(BlasEntry {
            parts: vec![dst],
            class,
            sizes: BlasSizes {
                as_bytes: size,
                ..sizes
            },
            skinned: None,
            static_inputs: inputs,
            spares: Vec::new(),
            shading,
            shading_plain,
            compacted_size: Some(size),
            compacted: false,
            recorded: frame,
            gpu_quality: None,
        });
        self.frame_copies.push((blas, copy));
        Ok(copy)
    }

    /// Destroys an input buffer this call created, if any (all-or-nothing failure paths).
    fn destroy_all(&mut self, b: Option<GpuBuffer>) {
        if let Some(b) = b {
            self.destroy(Retired::BlasBuffer(b));
        }
    }

    pub(super) fn retire_blas(&mut self, blas: BlasHandle, last_used_frame: u64) {
        let Some(e) = self.take(blas) else {
            tracing::warn!(?blas, "free of an unknown BLAS");
            return;
        };
        // Not before the frame whose commands last used it (a compaction from it in the
        // frame that frees it, say, with the TLAS that last named it an earlier frame's).
        let last_used_frame = last_used_frame.max(e.recorded);
        if e.parts.len() > 1 {
            self.split_parts.remove(&e.parts[0].address);
        }
        if e.shading_plain {
            self.retired_shading
                .insert(e.parts[0].address, (last_used_frame, e.shading));
        }
        let objects: Vec<Retired> = e.into_owned().collect();
        // Keep the queue ordered by frame: frees of older frames may arrive late, and go in
        // after the entries of their frame (no sort of the whole queue per free).
        let at = self
            .retiring
            .partition_point(|(f, _)| *f <= last_used_frame);
        for (k, o) in objects.into_iter().enumerate() {
            self.retiring.insert(at + k, (last_used_frame, o));
        }
    }
}

//! The BLAS handle registry (generations, split parts, lookup by address), the shading
//! lookups, skinned pose buffers and injected faults.

use super::*;

impl VulkanBackend {
    pub(super) fn entry(&self, h: BlasHandle) -> Option<&BlasEntry> {
        self.blases.get(key_of(h))
    }

    /// The device address of a live BLAS, or [`VulkanError::StaleHandle`] for a freed one
    /// (whose slot may now hold a newer BLAS).
    pub fn resolve_blas(&self, h: BlasHandle) -> VkResult<u64> {
        self.entry(h)
            .map(|e| e.parts[0].address)
            .ok_or_else(|| VulkanError::StaleHandle {
                what: "BLAS",
                detail: format!("{:?} was freed", key_of(h)),
            })
    }

    /// Whether the BLAS at `address` still exists on the device: live, a skinned BLAS's earlier
    /// refit target (separate refit targets), or freed and waiting for the frames that may use
    /// it (retiring), not yet destroyed.
    pub fn is_blas_address_retained(&self, address: u64) -> bool {
        self.is_live_blas_address(address)
            || self
                .blases
                .values()
                .any(|e| e.spares.iter().any(|a| a.address == address))
            || self
                .retiring
                .iter()
                .any(|(_, r)| matches!(r, Retired::BlasAccel(a) if a.address == address))
    }

    /// Test support: a copy of the buffer at `address` that the backend owns as a BLAS input
    /// (static vertices or indices, a skinned pose or index buffer), live or retiring.
    #[doc(hidden)]
    pub fn input_buffer_bytes(&self, address: u64) -> Option<Vec<u8>> {
        if address == 0 {
            return None;
        }
        let skinned = self.blases.values().flat_map(|e| {
            e.skinned
                .iter()
                .flat_map(|s| s.indices.iter().chain(&s.poses))
        });
        let retiring = self.retiring.iter().filter_map(|(_, r)| match r {
            Retired::BlasBuffer(b) => Some(b),
            _ => None,
        });
        let buffer = skinned
            .chain(retiring)
            .find(|b| (b.address..b.address + b.size).contains(&address))
            .and_then(|b| {
                b.mapped()
                    .map(|m| m[(address - b.address) as usize..].to_vec())
            });
        // A static BLAS's inputs are a range of the input arena; its indices start inside it.
        let statics = self
            .blases
            .values()
            .filter_map(|e| e.static_inputs.as_ref());
        let retiring = self.retiring.iter().filter_map(|(_, r)| match r {
            Retired::BlasInput(r) => Some(r),
            _ => None,
        });
        buffer.or_else(|| {
            statics
                .map(|s| &s.range)
                .chain(retiring)
                .find(|r| (r.address..r.address + r.size).contains(&address))
                .and_then(|r| {
                    let from = (address - r.address) as usize;
                    self.inputs.bytes(r).map(|b| b[from..].to_vec())
                })
        })
    }

    pub(super) fn insert(&mut self, e: BlasEntry) -> BlasHandle {
        let address = e.parts[0].address;
        let key = self.blases.insert(e);
        self.by_address.insert(address, key);
        BlasHandle(slotmap::Key::data(&key).as_ffi())
    }

    pub(super) fn take(&mut self, h: BlasHandle) -> Option<BlasEntry> {
        let e = self.blases.remove(key_of(h))?;
        for a in e.parts.iter().take(1).chain(&e.spares) {
            self.by_address.remove(&a.address);
        }
        Some(e)
    }

    /// Injected faults that have not struck yet.
    #[doc(hidden)]
    pub fn pending_faults(&self) -> usize {
        self.faults.len()
    }

    /// Disarms every injected fault.
    #[doc(hidden)]
    pub fn clear_faults(&mut self) {
        self.faults.clear();
    }

    /// Arms a fault: the next call at `at` fails with `error` and does nothing else
    /// (`DeviceLost` also marks the device lost, as a real loss would). For tests of the error
    /// paths on a real device.
    pub fn inject_fault(&mut self, at: FaultPoint, error: BackendError) {
        self.faults.push((at, error));
    }

    pub(super) fn fault(&mut self, at: FaultPoint) -> BackendResult<()> {
        match self.faults.iter().position(|(p, _)| *p == at) {
            Some(i) => {
                let (_, e) = self.faults.remove(i);
                self.lost |= e == BackendError::DeviceLost;
                Err(e)
            }
            None => Ok(()),
        }
    }

    /// A new host-visible build-input buffer (counted against the BLAS memory limit) holding
    /// `bytes`: a copy of new geometry, timed apart in its `upload_geometry` span (reported
    /// beside `update`, not in it).
    pub(super) fn upload_input(&mut self, name: &str, bytes: &[u8]) -> BackendResult<GpuBuffer> {
        let mut b = self.create_buffer(
            BufferDesc {
                name,
                size: bytes.len().max(4) as u64,
                usage: BUILD_INPUT_USAGE,
                memory: MemoryKind::Upload,
            },
            true,
        )?;
        tracing::trace_span!("upload_geometry").in_scope(|| b.write(0, bytes));
        Ok(b)
    }

    /// A static BLAS's positions and indices in one new host-visible buffer.
    pub(super) fn upload_static_inputs(
        &mut self,
        positions: &[[f32; 3]],
        indices: &[u32],
    ) -> BackendResult<StaticInputs> {
        let positions_bytes = std::mem::size_of_val(positions) as u64;
        let at = StaticInputs::index_offset(positions_bytes);
        let size = (at + std::mem::size_of_val(indices) as u64).max(4);
        self.reserve(size, true)?;
        let range = match self.inputs.alloc(&self.ctx, size) {
            Ok(r) => r,
            Err(e) => {
                self.unreserve(size, true);
                return Err(backend_err(e));
            }
        };
        tracing::trace_span!("upload_geometry").in_scope(|| {
            let dst = self
                .inputs
                .bytes_mut(&range)
                .expect("the input arena is host-visible");
            let p: &[u8] = bytemuck::cast_slice(positions);
            dst[..p.len()].copy_from_slice(p);
            let i: &[u8] = bytemuck::cast_slice(indices);
            dst[at as usize..at as usize + i.len()].copy_from_slice(i);
        });
        self.counters.input_upload_bytes += positions_bytes + std::mem::size_of_val(indices) as u64;
        Ok(StaticInputs {
            range,
            positions_bytes,
        })
    }

    /// A new host-visible buffer holding `positions` (a skinned BLAS's pose).
    pub(super) fn pose_buffer(&mut self, positions: &[[f32; 3]]) -> BackendResult<GpuBuffer> {
        let b = self.upload_input("skinned pose", bytemuck::cast_slice(positions))?;
        self.counters.pose_upload_bytes += (positions.len() * 12) as u64;
        Ok(b)
    }

    /// Writes a refit's pose into the next buffer of the BLAS's ring (allocating it while the
    /// ring is short) and points the shading at it; returns its device address.
    pub(super) fn write_pose(
        &mut self,
        blas: BlasHandle,
        positions: &[[f32; 3]],
    ) -> BackendResult<u64> {
        let ring = self.desc.frames_in_flight as usize + 1;
        let key = key_of(blas);
        let short = self
            .blases
            .get(key)
            .and_then(|e| e.skinned.as_ref())
            .is_some_and(|sk| sk.poses.len() < ring);
        let fresh = if short {
            Some(self.pose_buffer(positions)?)
        } else {
            None
        };
        let e = self.blases.get_mut(key).ok_or(Misuse::UnknownBlas(blas))?;
        let sk = e.skinned.as_mut().ok_or(Misuse::NotSkinned(blas))?;
        let address = match fresh {
            Some(b) => {
                let a = b.address;
                sk.poses.push(b);
                a
            }
            None => {
                // Written `ring` refits ago: every frame that read it has completed.
                let b = &mut sk.poses[sk.next % ring];
                // A copy of new geometry: timed apart (reported beside `update`, not in it).
                tracing::trace_span!("upload_geometry")
                    .in_scope(|| b.write(0, bytemuck::cast_slice(positions)));
                self.counters.pose_upload_bytes += (positions.len() * 12) as u64;
                b.address
            }
        };
        sk.next += 1;
        e.shading.0 = address;
        Ok(address)
    }

    /// The positions the shading of the BLAS at `blas_address` reads now, copied back from
    /// its host-visible buffer (tests check them against the last pose or the mesh).
    pub fn shading_positions(&self, blas_address: u64) -> Option<Vec<[f32; 3]>> {
        let key = *self.by_address.get(&blas_address)?;
        let e = self.blases.get(key)?;
        let bytes = match &e.static_inputs {
            Some(s) => &self.inputs.bytes(&s.range)?[..s.positions_bytes as usize],
            None => e
                .skinned
                .iter()
                .flat_map(|sk| sk.poses.iter())
                .find(|b| b.address == e.shading.0)?
                .mapped()?,
        };
        let n = bytes.len() / 12;
        Some(
            bytes[..n * 12]
                .chunks_exact(12)
                .map(|c| {
                    let f = |i: usize| f32::from_le_bytes(c[i..i + 4].try_into().expect("4 bytes"));
                    [f(0), f(4), f(8)]
                })
                .collect(),
        )
    }

    /// Device addresses of the positions (`[f32; 3]`) and `u32` indices a shader should read
    /// for the BLAS whose (first-part) device address is `blas_address` — the address in a TLAS
    /// instance record. For a skinned BLAS the positions are this frame's pose. Valid while the
    /// frame that recorded the record is in flight. Geometry in the engine's own buffers
    /// (`LodGeometry::Device`, `set_skinned_pose_device`) is read there, at the engine's
    /// addresses, when it is `f32x3` 12 bytes apart with `u32` indices; in any other format or
    /// stride the answer is `None` (the engine shades from its own vertex data).
    pub fn shading_geometry(&self, blas_address: u64) -> Option<(u64, u64)> {
        let Some(&key) = self.by_address.get(&blas_address) else {
            // Freed, but a frame in flight may still name it.
            return self.retired_shading.get(&blas_address).map(|&(_, s)| s);
        };
        self.blases
            .get(key)
            .filter(|e| e.shading_plain)
            .map(|e| e.shading)
    }
}

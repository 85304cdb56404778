//! TLAS instance records in the `VkAccelerationStructureInstanceKHR` layout, and their
//! (parallel) assembly.

use bytemuck::{Pod, Zeroable};
use glam::Affine3A;

/// VK_GEOMETRY_INSTANCE_TRIANGLE_FACING_CULL_DISABLE_BIT_KHR.
pub const INSTANCE_TRIANGLE_FACING_CULL_DISABLE: u8 = 0x1;
/// VK_GEOMETRY_INSTANCE_TRIANGLE_FLIP_FACING_BIT_KHR.
pub const INSTANCE_TRIANGLE_FLIP_FACING: u8 = 0x2;
/// VK_GEOMETRY_INSTANCE_FORCE_OPAQUE_BIT_KHR.
pub const INSTANCE_FORCE_OPAQUE: u8 = 0x4;
/// VK_GEOMETRY_INSTANCE_FORCE_NO_OPAQUE_BIT_KHR.
pub const INSTANCE_FORCE_NO_OPAQUE: u8 = 0x8;

/// One 64-byte TLAS instance, bit-compatible with `VkAccelerationStructureInstanceKHR`.
///
/// ```
/// use rtstream_as_manager::record::{TlasInstance, INSTANCE_FORCE_OPAQUE};
/// let r = TlasInstance::new(&glam::Affine3A::IDENTITY, 7, 0xff, 1, INSTANCE_FORCE_OPAQUE, 0x1000);
/// assert_eq!(std::mem::size_of::<TlasInstance>(), 64);
/// assert_eq!((r.custom_index(), r.mask(), r.sbt_offset(), r.flags()), (7, 0xff, 1, 0x4));
/// ```
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct TlasInstance {
    /// `VkTransformMatrixKHR`: 3x4 row-major (object to world).
    pub transform: [f32; 12],
    /// `instanceCustomIndex:24 | mask:8 << 24`.
    pub custom_index_and_mask: u32,
    /// `instanceShaderBindingTableRecordOffset:24 | flags:8 << 24`.
    pub sbt_offset_and_flags: u32,
    /// `accelerationStructureReference`: the BLAS device address.
    pub blas_address: u64,
}

const _: () = assert!(std::mem::size_of::<TlasInstance>() == 64);

/// 3x4 row-major matrix of an affine transform.
pub fn transform_rows(t: &Affine3A) -> [f32; 12] {
    let m = t.matrix3;
    let p = t.translation;
    [
        m.x_axis.x, m.y_axis.x, m.z_axis.x, p.x, //
        m.x_axis.y, m.y_axis.y, m.z_axis.y, p.y, //
        m.x_axis.z, m.y_axis.z, m.z_axis.z, p.z,
    ]
}

impl TlasInstance {
    /// Packs a record. `custom_index` and `sbt_offset` must fit in 24 bits.
    pub fn new(
        t: &Affine3A,
        custom_index: u32,
        mask: u8,
        sbt_offset: u32,
        flags: u8,
        blas_address: u64,
    ) -> Self {
        debug_assert!(custom_index < (1 << 24), "customIndex must fit in 24 bits");
        debug_assert!(sbt_offset < (1 << 24), "SBT offset must fit in 24 bits");
        Self {
            transform: transform_rows(t),
            custom_index_and_mask: (custom_index & 0xff_ffff) | ((mask as u32) << 24),
            sbt_offset_and_flags: (sbt_offset & 0xff_ffff) | ((flags as u32) << 24),
            blas_address,
        }
    }

    /// instanceCustomIndex.
    pub fn custom_index(&self) -> u32 {
        self.custom_index_and_mask & 0xff_ffff
    }

    /// mask.
    pub fn mask(&self) -> u8 {
        (self.custom_index_and_mask >> 24) as u8
    }

    /// instanceShaderBindingTableRecordOffset.
    pub fn sbt_offset(&self) -> u32 {
        self.sbt_offset_and_flags & 0xff_ffff
    }

    /// flags.
    pub fn flags(&self) -> u8 {
        (self.sbt_offset_and_flags >> 24) as u8
    }
}

/// Appends `n` records from `f(i)` to `out`, split into `threads` chunks on rayon's pool
/// (created once per process, not per frame) when `n >= parallel_threshold`.
pub fn assemble<F>(
    n: usize,
    out: &mut Vec<TlasInstance>,
    threads: usize,
    parallel_threshold: usize,
    f: F,
) where
    F: Fn(usize) -> TlasInstance + Sync,
{
    if n < parallel_threshold || threads <= 1 {
        out.extend((0..n).map(&f));
        return;
    }
    let start = out.len();
    out.resize(start + n, TlasInstance::zeroed());
    let chunk = n.div_ceil(threads);
    use rayon::prelude::*;
    out[start..]
        .par_chunks_mut(chunk)
        .enumerate()
        .for_each(|(c, slice)| {
            let base = c * chunk;
            for (i, r) in slice.iter_mut().enumerate() {
                *r = f(base + i);
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Quat, Vec3};

    #[test]
    fn layout_and_transform_rows() {
        let t = Affine3A::from_scale_rotation_translation(
            Vec3::splat(2.0),
            Quat::IDENTITY,
            Vec3::new(1.0, 2.0, 3.0),
        );
        let r = TlasInstance::new(
            &t,
            0xab_cdef,
            0x81,
            0x12_3456,
            INSTANCE_FORCE_OPAQUE,
            0x00de_adbe_ef00,
        );
        assert_eq!(
            r.transform,
            [2.0, 0.0, 0.0, 1.0, 0.0, 2.0, 0.0, 2.0, 0.0, 0.0, 2.0, 3.0]
        );
        let bytes: &[u8] = bytemuck::bytes_of(&r);
        assert_eq!(bytes.len(), 64);
        assert_eq!(
            u32::from_le_bytes(bytes[48..52].try_into().unwrap()),
            0x81ab_cdef
        );
        assert_eq!(
            u32::from_le_bytes(bytes[52..56].try_into().unwrap()),
            0x0412_3456
        );
        assert_eq!(
            u64::from_le_bytes(bytes[56..64].try_into().unwrap()),
            0x00de_adbe_ef00
        );
    }

    #[test]
    fn parallel_assembly_matches_serial() {
        let f = |i: usize| TlasInstance::new(&Affine3A::IDENTITY, i as u32, 1, 0, 0, i as u64);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        assemble(1000, &mut a, 1, usize::MAX, f);
        assemble(1000, &mut b, 3, 10, f);
        assert_eq!(a, b);
        // Appends after what is there.
        assemble(10, &mut a, 1, usize::MAX, f);
        assemble(10, &mut b, 3, 2, f);
        assert_eq!(a, b);
        assert_eq!((a.len(), a[1000].custom_index()), (1010, 0));
    }
}

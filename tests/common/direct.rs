//! Helpers of the tests that drive `VulkanBackend` through `AsBackend` directly, as an engine
//! without the manager would (`backend_misuse.rs`, `engine_misuse.rs`).

use std::sync::Arc;

use glam::{Affine3A, Vec3};
use rtstream::as_manager::backend::vulkan::{VulkanBackend, VulkanBackendDesc, VulkanContext};
use rtstream::as_manager::backend::{
    AsBackend, BackendError, BackendResult, BlasBuild, BlasClass, BlasHandle, GeometryRef, Misuse,
};
use rtstream::as_manager::record::{TlasInstance, INSTANCE_FORCE_OPAQUE};

/// An own-submit backend with 2 frames in flight.
pub fn backend(ctx: &Arc<VulkanContext>) -> VulkanBackend {
    VulkanBackend::new(
        ctx.clone(),
        VulkanBackendDesc {
            frames_in_flight: 2,
            ..VulkanBackendDesc::default()
        },
    )
    .expect("backend")
}

/// CPU geometry over `positions` and `indices` (counts from the slices).
pub fn geom<'a>(positions: &'a [[f32; 3]], indices: &'a [u32]) -> GeometryRef<'a> {
    GeometryRef {
        vertex_count: positions.len() as u32,
        triangle_count: (indices.len() / 3) as u32,
        positions: Some(positions),
        indices: Some(indices),
        device_vertices: None,
        device_indices: None,
        opaque: true,
    }
}

/// One build of `g` as `class`, sized by the backend.
pub fn build_one(
    b: &mut VulkanBackend,
    g: GeometryRef<'_>,
    class: BlasClass,
) -> BackendResult<BlasHandle> {
    let sizes = b.blas_sizes(&g, class);
    b.build_blases(&[BlasBuild {
        geometry: g,
        class,
        sizes,
    }])
    .map(|h| h[0])
}

/// An opaque record of the BLAS at `address`, `x` metres along x.
pub fn record_at(address: u64, custom: u32, x: f32) -> TlasInstance {
    TlasInstance::new(
        &Affine3A::from_translation(Vec3::new(x, 0.0, 0.0)),
        custom,
        0xff,
        0,
        INSTANCE_FORCE_OPAQUE,
        address,
    )
}

/// An opaque record of the BLAS at `address`, in place.
pub fn record(address: u64, custom: u32) -> TlasInstance {
    record_at(address, custom, 0.0)
}

/// Pixels of `hits` ((custom index, primitive) each) on instance `custom`.
pub fn hits_of(hits: &[(u32, u32)], custom: u32) -> usize {
    hits.iter().filter(|h| h.0 == custom).count()
}

/// Whether `r` is the backend refusing the call as `m`.
pub fn refused<T>(r: &BackendResult<T>, m: Misuse) -> bool {
    matches!(r, Err(BackendError::Misuse(x)) if *x == m)
}

/// The panic message of a `catch_unwind` result.
pub fn panic_text(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<String>()
        .cloned()
        .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_default()
}

/// Collected defects of a test (several aspects of one misuse are checked before failing).
#[derive(Default)]
pub struct Defects(Vec<String>);

impl Defects {
    /// Notes `what` unless `ok`.
    pub fn check(&mut self, ok: bool, what: impl Into<String>) {
        if !ok {
            let w = what.into();
            eprintln!("DEFECT: {w}");
            self.0.push(w);
        }
    }

    /// The validation layer's messages so far, as defects.
    pub fn validation(&mut self, ctx: &VulkanContext) {
        let log = ctx.validation_log();
        if log.failure_count() > 0 {
            for m in log.messages() {
                self.check(false, format!("validation: {m}"));
            }
        }
    }

    /// Fails the test with every defect noted.
    pub fn assert_none(self) {
        assert!(self.0.is_empty(), "defects:\n{}", self.0.join("\n"));
    }
}

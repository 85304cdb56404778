//! [`TlasRef`]: what is handed out for tracing a top-level acceleration structure, and the
//! context's check that one still names what it named when it was handed out.
//!
//! A raw `vk::AccelerationStructureKHR` cannot say that: once a TLAS is destroyed, the driver
//! may give its handle value to a newer one, and a manager's TLAS slot is rebuilt in place
//! `frames_in_flight` frames later. So each TLAS gets a serial when it is created and another
//! each time a build or update into it is recorded ([`VulkanContext::cmd_build_tlas`]); the
//! context maps each live TLAS to its current serial. Serials come from one process-wide
//! counter and are never reused, so a ref of another context's TLAS never matches either,
//! whatever handle values the two devices use.

use std::sync::atomic::{AtomicU64, Ordering};

use ash::vk;

use crate::backend::vulkan::device::accel::AccelStruct;
use crate::backend::vulkan::device::context::VulkanContext;

/// A top-level acceleration structure as one build of it: the raw handle and the serial the
/// context gave it when that build was recorded (or when it was created).
///
/// Returned by [`VulkanBackend::tlas`](crate::backend::vulkan::VulkanBackend::tlas),
/// [`StaticScene::tlas_ref`](crate::backend::vulkan::StaticScene::tlas_ref) and
/// [`VulkanContext::tlas_ref`], and taken by the renderer. It cannot be made from a raw handle
/// outside this crate. [`VulkanContext::is_live_tlas`] is true only while the TLAS is alive
/// and has not been built again since: a stale ref is refused, never read as a newer TLAS
/// that has the same handle value. Use [`raw`](Self::raw) where Vulkan wants the handle
/// (descriptor writes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct TlasRef {
    raw: vk::AccelerationStructureKHR,
    serial: u64,
}

impl TlasRef {
    /// A ref of `raw` at `serial` (crate-internal: refs come from the live map, and tests).
    pub(crate) fn new(raw: vk::AccelerationStructureKHR, serial: u64) -> Self {
        Self { raw, serial }
    }

    /// The `vk::AccelerationStructureKHR` handle, for descriptor writes.
    pub fn raw(self) -> vk::AccelerationStructureKHR {
        self.raw
    }

    /// The serial of the build this ref names (unique in the process, never 0).
    pub fn serial(self) -> u64 {
        self.serial
    }
}

/// The next TLAS serial: process-wide, so no two TLASes or builds of any context share one.
static NEXT_SERIAL: AtomicU64 = AtomicU64::new(1);

fn next_serial() -> u64 {
    NEXT_SERIAL.fetch_add(1, Ordering::Relaxed)
}

impl VulkanContext {
    /// Records a TLAS created on this context with a fresh serial.
    pub(crate) fn tlas_created(&self, raw: vk::AccelerationStructureKHR) {
        self.live_tlases.lock().insert(raw, next_serial());
        tracing::trace!(?raw, "TLAS created");
    }

    /// Gives a TLAS of this context a fresh serial: a build or update into it was recorded,
    /// so refs of its earlier contents are stale. (Not one of this context's TLASes: nothing.)
    pub(crate) fn tlas_rebuilt(&self, raw: vk::AccelerationStructureKHR) {
        if let Some(serial) = self.live_tlases.lock().get_mut(&raw) {
            *serial = next_serial();
        }
    }

    /// Forgets a TLAS (destroyed); nothing for another kind of acceleration structure.
    pub(crate) fn tlas_destroyed(&self, raw: vk::AccelerationStructureKHR) {
        self.live_tlases.lock().remove(&raw);
    }

    /// The ref of `tlas` as it is now (its last recorded build), or None when it is not a
    /// live top-level acceleration structure of this context (a BLAS, or another context's).
    pub fn tlas_ref(&self, tlas: &AccelStruct) -> Option<TlasRef> {
        self.live_tlas_serial(tlas.raw)
            .map(|serial| TlasRef::new(tlas.raw, serial))
    }

    /// Whether `tlas` names a top-level acceleration structure of this context that is alive
    /// and has not been built again since the ref was taken: what the renderer checks before
    /// it traces. False for a destroyed TLAS, another context's, and a stale ref whose
    /// handle value a newer TLAS (or build) now has.
    pub fn is_live_tlas(&self, tlas: TlasRef) -> bool {
        self.live_tlas_serial(tlas.raw) == Some(tlas.serial)
    }

    /// The current serial of the live TLAS of this context whose handle value is `raw`, if
    /// there is one: to tell why a ref is not live (a lower serial than this: stale; a higher
    /// one: another context's).
    pub fn live_tlas_serial(&self, raw: vk::AccelerationStructureKHR) -> Option<u64> {
        if raw == vk::AccelerationStructureKHR::null() {
            return None;
        }
        self.live_tlases.lock().get(&raw).copied()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::vulkan::device::context::{ContextDesc, Validation};

    /// A context on the machine's Vulkan device (lavapipe here) with the validation layer
    /// required, as the workspace's GPU tests make theirs (`tests/common/mod.rs`).
    fn context() -> VulkanContext {
        let desc = ContextDesc {
            app_name: "rtstream as-manager unit tests".into(),
            validation: Validation::Required,
            require_ray_query: true,
            ..ContextDesc::default()
        };
        VulkanContext::new(&desc).unwrap_or_else(|e| panic!("Vulkan context: {e}"))
    }

    fn new_tlas(ctx: &VulkanContext, name: &str) -> AccelStruct {
        let flags = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE;
        let size = ctx.tlas_sizes(1, flags).storage;
        ctx.create_accel(vk::AccelerationStructureTypeKHR::TOP_LEVEL, size, name)
            .expect("TLAS")
    }

    /// A TLAS destroyed and another created (the driver may give it the same handle value):
    /// the old ref, and a ref with the new handle value but the old serial, are not live; the
    /// new one is. Serials are never reused.
    #[test]
    fn a_stale_tlas_ref_is_not_live() {
        let ctx = context();
        let a = new_tlas(&ctx, "TLAS a");
        let old = ctx.tlas_ref(&a).expect("a live TLAS has a ref");
        assert!(ctx.is_live_tlas(old));
        ctx.destroy_accel(a);
        assert!(!ctx.is_live_tlas(old), "a destroyed TLAS is not live");
        assert_eq!(ctx.live_tlas_serial(old.raw()), None);

        let b = new_tlas(&ctx, "TLAS b");
        let new = ctx.tlas_ref(&b).expect("a live TLAS has a ref");
        assert!(ctx.is_live_tlas(new), "the new TLAS is live");
        assert!(new.serial() > old.serial(), "serials are never reused");
        let forged = TlasRef::new(new.raw(), old.serial());
        assert!(
            !ctx.is_live_tlas(forged),
            "the new TLAS's handle value with the old serial is stale"
        );
        assert!(!ctx.is_live_tlas(old), "the old ref stays stale");
        // Whether or not the driver reused the handle value, the old ref never reads as `b`.
        eprintln!("handle value reused: {}", old.raw() == new.raw());

        ctx.destroy_accel(b);
        assert!(!ctx.is_live_tlas(new));
        assert_eq!(
            ctx.validation_log().failure_count(),
            0,
            "{:?}",
            ctx.validation_log().messages()
        );
    }

    /// A BLAS has no ref, and the null handle is never live.
    #[test]
    fn only_a_live_tlas_has_a_ref() {
        let ctx = context();
        let blas = ctx
            .create_accel(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, 4096, "BLAS")
            .expect("BLAS");
        assert_eq!(ctx.tlas_ref(&blas), None);
        ctx.destroy_accel(blas);
        assert!(!ctx.is_live_tlas(TlasRef::new(vk::AccelerationStructureKHR::null(), 1)));
        assert_eq!(ctx.validation_log().failure_count(), 0);
    }

    /// Recording a build into a TLAS makes refs of its earlier contents stale.
    #[test]
    fn a_rebuilt_tlas_has_a_new_ref() {
        let ctx = context();
        let t = new_tlas(&ctx, "TLAS rebuilt");
        let before = ctx.tlas_ref(&t).expect("live");
        ctx.tlas_rebuilt(t.raw);
        let after = ctx.tlas_ref(&t).expect("live");
        assert_ne!(before, after);
        assert!(!ctx.is_live_tlas(before) && ctx.is_live_tlas(after));
        ctx.destroy_accel(t);
        assert_eq!(ctx.validation_log().failure_count(), 0);
    }
}

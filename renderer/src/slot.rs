//! The resources one recorded frame in flight owns (`Renderer::record`): its own outputs,
//! instance buffer and timestamps, so a frame never writes what one still in flight reads.

use rtstream_as_manager::backend::vulkan::{GpuBuffer, QueryPool};

use crate::shading::TableState;

/// What one frame in flight owns.
#[derive(Debug)]
pub(crate) struct RenderSlot {
    /// The frame recorded into these resources last, and whether it was read back.
    pub(crate) frame: Option<u64>,
    pub(crate) taken: bool,
    pub(crate) size: (u32, u32),
    pub(crate) outputs: Vec<GpuBuffer>,
    pub(crate) instances: Option<GpuBuffer>,
    /// What `instances` holds of the shading table.
    pub(crate) table: TableState,
    pub(crate) timer: QueryPool,
    /// The timer's results, copied there on the GPU.
    pub(crate) times: GpuBuffer,
}

impl RenderSlot {
    pub(crate) fn destroy(self, ctx: &rtstream_as_manager::backend::vulkan::VulkanContext) {
        for b in self
            .outputs
            .into_iter()
            .chain(self.instances)
            .chain(std::iter::once(self.times))
        {
            ctx.destroy_buffer(b);
        }
        self.timer.destroy(ctx);
    }
}

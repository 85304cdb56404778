//! Writing a recorded frame's shading table: the whole table, or only what changed since the
//! table's previous frame ([`ShadingUpdate`], [`Renderer::record_update`]).
//!
//! Each frame in flight has its own instance buffer, written when the frame is recorded
//! (`RECORDED_SETS` of them, used in turn). A buffer therefore misses the changes of every
//! frame recorded into the other buffers since it was last written: each buffer keeps the
//! entries changed since then (`pending`), and a buffer whose list grows past a quarter of
//! the table, whose chain of versions broke (a version skipped, another table, or a whole
//! table recorded by [`Renderer::record`]), or that was just created is written whole.
//!
//! [`Renderer::record_update`]: crate::Renderer::record_update
//! [`Renderer::record`]: crate::Renderer::record

use rtstream_as_manager::backend::vulkan::GpuBuffer;

use crate::renderer::{shading_table, InstanceShading};

/// One frame's shading table and what changed in it since the same table's previous frame:
/// what lets [`Renderer::record_update`](crate::Renderer::record_update) write only the
/// changed entries of a frame's instance buffer, not the whole table (13.5 MB a frame in the
/// fly-through at ten times the default density).
///
/// The renderer checks the chain: `serial` must follow the serial of the update it recorded
/// last, of the same `table_id`; otherwise it writes the whole table, so a skipped or
/// foreign update costs time, never a wrong entry.
#[derive(Debug, Clone, Copy)]
pub struct ShadingUpdate<'a> {
    /// The whole table, indexed by customIndex (what [`Renderer::record`](crate::Renderer::record)
    /// takes).
    pub table: &'a [InstanceShading],
    /// Entries that differ from the previous version of the table, among those below the
    /// previous version's length (entries past it are new and written anyway). Duplicates and
    /// unchanged entries are allowed; entries past `table`'s end are ignored.
    pub changed: &'a [u32],
    /// Which table this is (one per table kept, e.g. `rtstream::ShadingTable`'s).
    pub table_id: u64,
    /// This version's number: `changed` is relative to version `serial - 1`.
    pub serial: u64,
}

/// What an instance buffer holds of the table, kept with the buffer.
#[derive(Debug, Default)]
pub(crate) struct TableState {
    /// Entries `..valid` hold the table as of the buffer's last write, but for `pending`.
    valid: usize,
    /// Entries changed since the buffer's last write.
    pending: Vec<u32>,
    /// The buffer must be written whole (new buffer, broken chain, too many changes).
    whole: bool,
}

/// The renderer's side of the chain of table versions.
#[derive(Debug, Default)]
pub(crate) struct TableChain {
    /// The (table_id, serial) recorded last; None after a whole table without versions.
    last: Option<(u64, u64)>,
}

impl TableState {
    /// A buffer just created holds nothing.
    pub(crate) fn fresh() -> Self {
        Self {
            valid: 0,
            pending: Vec::new(),
            whole: true,
        }
    }

    fn add(&mut self, changed: &[u32], len: usize) {
        if self.whole {
            return;
        }
        if self.pending.len() + changed.len() > len / 4 {
            self.whole = true;
            self.pending = Vec::new();
        } else {
            self.pending.extend_from_slice(changed);
        }
    }
}

impl TableChain {
    /// Brings every buffer's state up to `update` (before the frame's own buffer is
    /// written): their pending lists gain its changes, or they are marked whole when the
    /// chain broke.
    pub(crate) fn advance<'a>(
        &mut self,
        states: impl Iterator<Item = &'a mut TableState>,
        update: Option<&ShadingUpdate<'_>>,
    ) {
        let follows = matches!(
            (update, self.last),
            (Some(u), Some((id, s))) if u.table_id == id && u.serial == s.wrapping_add(1)
        );
        let len = update.map_or(0, |u| u.table.len());
        for st in states {
            match update {
                Some(u) if follows => st.add(u.changed, len),
                _ => {
                    st.whole = true;
                    st.pending = Vec::new();
                }
            }
            // Entries past this version's end may change before they come back: the
            // buffer's copy of them is stale from now on.
            st.valid = st.valid.min(len);
        }
        self.last = update.map(|u| (u.table_id, u.serial));
    }
}

/// Writes `instances` (the frame's table) into `buf`: whole when `st` says so, else its
/// pending entries and the entries past what the buffer held. Returns the entries written.
pub(crate) fn write_table(
    buf: &mut GpuBuffer,
    st: &mut TableState,
    instances: &[InstanceShading],
) -> usize {
    const ENTRY: usize = std::mem::size_of::<InstanceShading>();
    let table = shading_table(instances);
    let n = table.len();
    let dst = buf
        .mapped_mut()
        .expect("the instance buffer is host-visible");
    let dst = &mut dst[..n * ENTRY];
    // The one-entry fallback of an empty table is not a version of it.
    let written = if st.whole || instances.is_empty() {
        dst.copy_from_slice(bytemuck::cast_slice(table));
        n
    } else {
        let valid = st.valid.min(n);
        let mut written = n - valid;
        for &ci in &st.pending {
            let ci = ci as usize;
            if ci < valid {
                dst[ci * ENTRY..(ci + 1) * ENTRY].copy_from_slice(bytemuck::bytes_of(&table[ci]));
                written += 1;
            }
        }
        dst[valid * ENTRY..].copy_from_slice(bytemuck::cast_slice(&table[valid..]));
        written
    };
    st.pending.clear();
    st.whole = instances.is_empty();
    st.valid = if instances.is_empty() { 0 } else { n };
    written
}

//! The frame journal: what a frame changed that a failed frame must undo.
//!
//! A frame that fails after `begin_frame` (a backend error other than out-of-memory, which the
//! scheduler absorbs) is never submitted. `rollback` returns the manager to a state a retry of
//! the same frame number starts from:
//! - BLASes built in the frame are freed and their entries go back to the queue;
//! - compactions are undone (the source stays, the copy is freed; the source is only freed
//!   when a frame commits);
//! - refit bookkeeping (pose version, quality) goes back, so the retry refits again;
//! - the backend discards what it recorded (`AsBackend::abort_frame`).
//!
//! Decisions that need no GPU work stand: registry commands applied, entries released by
//! eviction (their BLASes retire after the frames that used them) and residency marks; a retry
//! makes the same decisions again.

use super::state::{EntryKey, EntryState, RefitState};
use super::AsManager;
use crate::backend::{AsBackend, BlasHandle};

/// A refit's bookkeeping before the frame.
#[derive(Debug)]
pub(crate) struct RefitUndo {
    pub entry: EntryKey,
    pub before: RefitState,
}

/// A compaction: the source (freed at commit) and the copy (freed on rollback).
#[derive(Debug)]
pub(crate) struct CompactUndo {
    pub entry: EntryKey,
    pub old: BlasHandle,
    pub old_bytes: u64,
    pub new: BlasHandle,
}

/// This frame's undoable changes.
#[derive(Debug, Default)]
pub(crate) struct FrameJournal {
    /// (entry, handle) of the BLASes built.
    pub built: Vec<(EntryKey, BlasHandle)>,
    pub refitted: Vec<RefitUndo>,
    pub compacted: Vec<CompactUndo>,
}

impl FrameJournal {
    pub fn clear(&mut self) {
        self.built.clear();
        self.refitted.clear();
        self.compacted.clear();
    }
}

impl<B: AsBackend> AsManager<B> {
    /// The frame was submitted: free the compaction sources.
    pub(crate) fn commit_frame(&mut self) {
        let frame = self.frame;
        for c in std::mem::take(&mut self.journal.compacted) {
            self.backend.free_blas(c.old, frame);
        }
        self.journal.clear();
    }

    /// Frees a BLAS the failed frame created: never submitted, so it retires against the
    /// newest completed frame (gone at the next `begin_frame` once one completed), and its
    /// bytes count as retiring until then (the retry's budget sees them).
    fn free_unsubmitted(&mut self, handle: BlasHandle, bytes: u64) {
        let last = self.backend.completed_frame().unwrap_or(0);
        self.backend.free_blas(handle, last);
        let i = self.retiring.partition_point(|&(f, _)| f <= last);
        self.retiring.insert(i, (last, bytes));
        self.retiring_bytes += bytes;
    }

    /// The frame failed: undo it (see the module docs), newest change first.
    pub(crate) fn rollback_frame(&mut self) {
        let frame = self.frame;
        // First: the backend forgets the frame's recorded work (its TLAS used nothing).
        self.backend.abort_frame();
        // The landmarks are a cache of decisions the retry makes again: all are looked at.
        self.records.clear();
        self.landmarks.write_back_detail(&mut self.grid, frame);
        self.landmarks.invalidate();
        let mut j = std::mem::take(&mut self.journal);
        for c in j.compacted.drain(..).rev() {
            let mut new_bytes = 0;
            let mut undone = false;
            if let Some(e) = self.tables.entries.get_mut(c.entry) {
                if e.handle == Some(c.new) {
                    undone = true;
                    new_bytes = e.bytes;
                    self.live_bytes = self.live_bytes - e.bytes + c.old_bytes;
                    e.bytes = c.old_bytes;
                    e.handle = Some(c.old);
                    e.address = self.backend.blas_address(c.old);
                    e.needs_compaction = true;
                    self.compact_pending.push(c.entry);
                }
            }
            if undone {
                self.tables.blas_changed(c.entry, self.frame);
            }
            // The manager counted the source as retiring: it is live again.
            if let Some(i) = self
                .retiring
                .iter()
                .rposition(|&(f, b)| f == frame && b == c.old_bytes)
            {
                self.retiring.remove(i);
                self.retiring_bytes -= c.old_bytes;
            }
            self.free_unsubmitted(c.new, new_bytes);
        }
        for r in j.refitted.drain(..).rev() {
            if let Some(e) = self.tables.entries.get_mut(r.entry) {
                e.refit = r.before;
            }
        }
        for (key, handle) in j.built.drain(..).rev() {
            let mut bytes = 0;
            let mut undone = false;
            if let Some(e) = self.tables.entries.get_mut(key) {
                if e.handle == Some(handle) {
                    undone = true;
                    bytes = e.bytes;
                    e.handle = None;
                    e.address = 0;
                    e.state = EntryState::Queued;
                    e.needs_compaction = false;
                    self.live_bytes -= e.bytes;
                    self.built_count -= 1;
                    e.bytes = 0;
                }
            }
            if undone {
                self.tables.blas_changed(key, self.frame);
            }
            self.free_unsubmitted(handle, bytes);
        }
        self.journal = j;
    }
}

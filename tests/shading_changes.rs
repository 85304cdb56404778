//! The shading table kept with the manager's record changes
//! ([`rtstream::ShadingTable::update_changes`], `AsManager::record_changes`): a small baked
//! world streamed along a walk with teleports into the manager (model backend, geometry
//! required), the far field's landmarks on. Every frame the table kept with the changes
//! equals a fresh [`WorldBridge::shading`] on each entry the records name and is colour-only
//! elsewhere, and the entries it lists bring its previous version to this one; most updates
//! look only at what the changes list, and one that missed an update looks at every record.

mod common;

use glam::Vec3;
use rtstream::as_manager::backend::model::ModelBackend;
use rtstream::as_manager::{AsManager, FrameInput, Viewpoint};
use rtstream::renderer::InstanceShading;
use rtstream::streaming::World;
use rtstream::{ShadingTable, WorldBridge};

#[test]
fn a_table_kept_with_the_record_changes_matches_a_fresh_one() {
    let (dir, size) = common::baked_small("shading_changes", 12, 5);
    let stream = common::small_world_stream();
    let mut world = World::open(&dir, stream).expect("open");
    let mut bridge = WorldBridge::new(world.manifest());
    let mut backend = ModelBackend::lavapipe();
    backend.require_geometry = true;
    // Short radii: most loaded instances lie beyond r2, where the landmarks keep them.
    let mut m = AsManager::new(common::lavapipe_config(30.0, 45.0), backend).unwrap();
    let mut kept = ShadingTable::default();
    let mut previous: Vec<InstanceShading> = Vec::new();
    let (mut delta_updates, mut with_landmarks, mut looked_less) = (0u32, 0u32, 0u32);
    let frames = 240u64;
    for frame in 0..frames {
        // A walk along x, a teleport every 80 frames.
        let start = Vec3::new(size * (0.2 + 0.25 * (frame / 80) as f32), 3.0, size * 0.4);
        let eye = start + Vec3::new((frame % 80) as f32 * 2.0, 0.0, 0.0);
        let events = world.update(frame, &[eye.into()]);
        bridge.apply(&m, &events);
        let cams = [Viewpoint::new(eye, Vec3::X)];
        let out = m.update(FrameInput {
            frame,
            cameras: &cams,
        });
        let records = out.expect("update").instances.to_vec();
        // Geometry answers that differ per BLAS and change for some of them every 40 frames
        // (as a backend's answer changes when a BLAS's storage is reused).
        let epoch = frame / 40;
        let geometry = move |addr: u64| ((addr >> 4) % 5 != epoch % 5).then_some((addr, !addr));
        if frame == 150 {
            // This update is missed: the next must look at every record.
            continue;
        }
        let changes = m.record_changes().expect("a successful update has changes");
        assert_eq!(changes.frame, frame);
        assert!(changes.is_well_formed(), "frame {frame}: {changes:?}");
        let (stable, listed) = (changes.stable, changes.changed.len());
        let fresh = bridge.shading(&records, geometry);
        let up = kept.update_changes(&bridge, m.records(), Some(changes), geometry);
        let table = up.table.to_vec();
        let changed = up.changed.to_vec();
        let full = kept.last_update_was_full();
        if frame == 151 {
            assert!(full, "the update after a missed one looks at every record");
        }
        if !full {
            delta_updates += 1;
            with_landmarks += u32::from(stable > 0 && listed > 0);
            looked_less += u32::from(listed + (records.len() - stable) < records.len());
        }
        common::assert_table_matches_fresh(frame, &records, &table, &fresh);
        common::assert_changes_bring(frame, &previous, &table, &changed);
        previous = table;
    }
    let _ = std::fs::remove_dir_all(&dir);
    eprintln!(
        "{delta_updates} of {frames} updates by the changes ({with_landmarks} with landmark \
         changes, {looked_less} looking at fewer than all records), {} full",
        kept.full_updates()
    );
    assert!(
        delta_updates as u64 >= frames * 3 / 4,
        "most updates look only at the changes: {delta_updates} of {frames}"
    );
    assert!(with_landmarks >= 20, "the walk changes landmark records");
    assert!(looked_less >= 20, "the changes skip records");
}

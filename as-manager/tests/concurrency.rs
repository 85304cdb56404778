//! Registration from several threads while `update` runs: four threads register meshes, add,
//! move and remove instances through `Registrar` clones, with random pauses, while the owning
//! thread keeps updating. Nothing deadlocks, nothing is lost, and once the frames settle the
//! TLAS is the one a serial run of the same operations gives (each thread works on its own
//! meshes and instances, so any interleaving must end in the same state).

use std::collections::BTreeSet;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use glam::{Affine3A, Vec3};
use rand_xoshiro::rand_core::{RngCore, SeedableRng};
use rand_xoshiro::SplitMix64;
use rtstream_as_manager::backend::model::ModelBackend;
use rtstream_as_manager::synth::counts_chain;
use rtstream_as_manager::*;

const THREADS: u32 = 4;
const OPS: u32 = 300;

/// One thread's work: its own meshes and instances, in program order; returns how many of its
/// instances are live at the end. `pause` runs between operations (random short sleeps in the
/// concurrent run, nothing in the serial one).
fn work(r: &Registrar, t: u32, mut pause: impl FnMut()) -> usize {
    let mut rng = SplitMix64::seed_from_u64(0x5EED + u64::from(t));
    let mut meshes = Vec::new();
    for k in 0..3 {
        let m = r
            .register_mesh(MeshDesc::new(
                format!("t{t}m{k}"),
                MeshKind::Static,
                1.0,
                counts_chain(200 + 100 * k, 2, 0.01),
            ))
            .unwrap();
        meshes.push(m);
    }
    let mut live: Vec<(InstanceId, u32)> = Vec::new();
    for i in 0..OPS {
        pause();
        let pos = |rng: &mut SplitMix64| {
            Vec3::new(
                (rng.next_u64() % 80) as f32 - 40.0,
                0.0,
                (rng.next_u64() % 80) as f32 - 40.0,
            )
        };
        match rng.next_u64() % 4 {
            0 | 1 => {
                let mesh = meshes[(rng.next_u64() % 3) as usize];
                let mut d = InstanceDesc::new(mesh, Affine3A::from_translation(pos(&mut rng)));
                d.custom_index = t * 10_000 + i;
                live.push((r.add_instance(d).unwrap(), t * 10_000 + i));
            }
            2 if !live.is_empty() => {
                let (id, _) = live[(rng.next_u64() % live.len() as u64) as usize];
                r.set_transform(id, Affine3A::from_translation(pos(&mut rng)))
                    .unwrap();
            }
            3 if !live.is_empty() => {
                let (id, _) = live.swap_remove((rng.next_u64() % live.len() as u64) as usize);
                r.remove_instance(id).unwrap();
            }
            _ => {}
        }
    }
    live.len()
}

fn config() -> Config {
    let mut c = Config::default();
    c.cull.mode = CullMode::Off;
    c.residency.create_threshold = 0;
    c.freeze_cost_model = true;
    c.build.max_primitives = 1_000_000;
    c.build.max_gpu_ms = 1_000.0;
    c
}

/// The settled TLAS: (customIndex, translation bits) of every record.
fn settle(m: &mut AsManager<ModelBackend>, from: u64) -> BTreeSet<(u32, [u32; 3])> {
    let cams = [Viewpoint::new(Vec3::ZERO, Vec3::Z)];
    let mut set = BTreeSet::new();
    for f in from..from + 12 {
        let out = m
            .update(FrameInput {
                frame: f,
                cameras: &cams,
            })
            .unwrap();
        set = out
            .instances
            .iter()
            .map(|r| {
                let t = r.transform;
                (
                    r.custom_index(),
                    [t[3].to_bits(), t[7].to_bits(), t[11].to_bits()],
                )
            })
            .collect();
    }
    m.check_invariants().unwrap();
    set
}

#[test]
fn threads_register_while_update_runs_and_the_result_is_the_serial_one() {
    // Concurrent.
    let mut m = AsManager::new(config(), ModelBackend::lavapipe()).unwrap();
    let done = Arc::new(AtomicBool::new(false));
    let handles: Vec<_> = (0..THREADS)
        .map(|t| {
            let r = m.registrar();
            std::thread::spawn(move || {
                // Pauses from a PRNG of their own: the operations stay those of the serial run.
                let mut jitter = SplitMix64::seed_from_u64(0xD1CE + u64::from(t));
                let _ = work(&r, t, || {
                    if jitter.next_u64() % 8 == 0 {
                        std::thread::sleep(std::time::Duration::from_micros(
                            jitter.next_u64() % 300,
                        ));
                    }
                });
            })
        })
        .collect();
    let cams = [Viewpoint::new(Vec3::ZERO, Vec3::Z)];
    let mut frame = 0;
    let watcher = {
        let done = done.clone();
        std::thread::spawn(move || {
            for h in handles {
                h.join().expect("a registering thread panicked");
            }
            done.store(true, Ordering::SeqCst);
        })
    };
    let mut frames_during = 0;
    while !done.load(Ordering::SeqCst) {
        m.update(FrameInput {
            frame,
            cameras: &cams,
        })
        .unwrap();
        m.check_invariants().unwrap();
        frame += 1;
        frames_during += 1;
    }
    watcher.join().unwrap();
    let concurrent = settle(&mut m, frame);

    // Serial: the same operations, thread after thread.
    let mut s = AsManager::new(config(), ModelBackend::lavapipe()).unwrap();
    let mut expected = 0;
    for t in 0..THREADS {
        expected += work(&s.registrar(), t, || {});
    }

    let serial = settle(&mut s, 0);

    assert!(frames_during > 0);
    assert_eq!(
        serial.len(),
        expected,
        "the serial run holds every live instance"
    );
    assert_eq!(
        concurrent.len(),
        expected,
        "no registration lost ({frames_during} frames ran meanwhile)"
    );

    let only_c: Vec<_> = concurrent.difference(&serial).take(10).collect();
    let only_s: Vec<_> = serial.difference(&concurrent).take(10).collect();
    assert_eq!(
        concurrent, serial,
        "the same final TLAS as the serial run: only concurrent {only_c:?}, only serial {only_s:?}"
    );
}

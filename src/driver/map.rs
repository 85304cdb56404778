//! A top-down map of one frame: levels loaded, instances placed, instances in the TLAS, the
//! r1/r2/streaming circles and the camera path so far.

use std::path::Path;

use glam::{Vec2, Vec3};
use rtstream_as_manager::record::TlasInstance;
use rtstream_as_manager::Config;
use rtstream_streaming::{LevelId, Manifest};

use crate::bridge::WorldBridge;
use crate::error::Result;

const SIZE: u32 = 640;

struct Canvas {
    px: Vec<[u8; 4]>,
    min: Vec2,
    scale: f32,
}

impl Canvas {
    fn to_px(&self, p: Vec3) -> (i32, i32) {
        let q = (Vec2::new(p.x, p.z) - self.min) * self.scale;
        (q.x as i32, q.y as i32)
    }

    fn put(&mut self, x: i32, y: i32, c: [u8; 4]) {
        if (0..SIZE as i32).contains(&x) && (0..SIZE as i32).contains(&y) {
            self.px[(y as u32 * SIZE + x as u32) as usize] = c;
        }
    }

    fn dot(&mut self, p: Vec3, r: i32, c: [u8; 4]) {
        let (x, y) = self.to_px(p);
        for dy in -r..=r {
            for dx in -r..=r {
                self.put(x + dx, y + dy, c);
            }
        }
    }

    fn circle(&mut self, centre: Vec3, radius_m: f32, c: [u8; 4]) {
        let r = radius_m * self.scale;
        let steps = (r * 8.0).clamp(32.0, 4096.0) as usize;
        let (cx, cy) = self.to_px(centre);
        for i in 0..steps {
            let a = i as f32 / steps as f32 * std::f32::consts::TAU;
            self.put(cx + (r * a.cos()) as i32, cy + (r * a.sin()) as i32, c);
        }
    }
}

/// Draws the map to `file` (PNG, 640x640).
#[allow(clippy::too_many_arguments)]
pub fn draw(
    file: &Path,
    manifest: &Manifest,
    loaded: impl Fn(LevelId) -> bool,
    bridge: &WorldBridge,
    records: &[TlasInstance],
    trail: &[Vec3],
    camera: Vec3,
    config: &Config,
    stream_radius: f32,
) -> Result<()> {
    let e = manifest.extent;
    let span = (e.max.x - e.min.x).max(e.max.z - e.min.z).max(1.0);
    let mut c = Canvas {
        px: vec![[18, 18, 24, 255]; (SIZE * SIZE) as usize],
        min: Vec2::new(e.min.x, e.min.z),
        scale: SIZE as f32 / span,
    };
    for (i, l) in manifest.levels.iter().enumerate() {
        if !loaded(LevelId(i as u32)) {
            continue;
        }
        let (x0, y0) = c.to_px(l.bounds.min);
        let (x1, y1) = c.to_px(l.bounds.max);
        for y in y0..y1 {
            for x in x0..x1 {
                c.put(x, y, [48, 52, 64, 255]);
            }
        }
    }
    // Placed (streamed in, not in the TLAS): red; in the TLAS: green.
    for (_, _, t) in bridge.placed_within(camera, f32::INFINITY) {
        c.dot(t.w_axis.truncate(), 0, [150, 40, 40, 255]);
    }
    for r in records {
        let p = Vec3::new(r.transform[3], r.transform[7], r.transform[11]);
        c.dot(p, 0, [60, 220, 90, 255]);
    }
    for w in trail.windows(2) {
        c.dot(w[0], 0, [240, 240, 240, 255]);
    }
    c.circle(camera, config.residency.r1, [90, 160, 255, 255]);
    c.circle(camera, config.residency.r2, [40, 100, 220, 255]);
    c.circle(camera, stream_radius, [200, 200, 80, 255]);
    c.dot(camera, 2, [255, 230, 0, 255]);
    rtstream_renderer::save_rgba_png(file, SIZE, SIZE, &c.px)?;
    Ok(())
}

//! Where `update` spends its time: a `tracing` layer that times the manager's and the Vulkan
//! backend's spans (`update` and the phases inside it), per policy and per frame.
//!
//! - Each span's time is its wall time between enter and exit on the thread that entered it;
//!   a span's path is its ancestors' names joined by `;` (`policy[managed];update;schedule`),
//!   the folded-stack format that `inferno-flamegraph` draws.
//! - When an `update` span closes, every path seen under it gets one sample (0 when a phase
//!   did not run that frame), so the percentiles of every phase are over the same frames.
//!   A derived row, `less geometry copies`, is `update` without the backend's
//!   `upload_geometry` spans (copies of new vertex and index data into upload buffers).
//! - `--profile FILE` in the examples writes the self times as folded stacks (microseconds)
//!   for a flame graph, and prints the per-phase table; the flythrough also writes each
//!   frame's phase times beside it (`FILE.frames.csv`; `NAME.folded` gives `NAME.frames.csv`),
//!   to see what makes the slowest frames.
//!
//! The layer only sees spans (`filter_fn(is_span)`), so the BLAS lifecycle events at `trace`
//! stay disabled, and costs two clock reads per span: about 20 spans a frame.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{Duration, Instant};

use parking_lot::Mutex;
use tracing::span::{Attributes, Id};
use tracing::Subscriber;
use tracing_subscriber::layer::Context;
use tracing_subscriber::registry::LookupSpan;
use tracing_subscriber::Layer;

/// A slow frame: its sample index, its `update` ms, and the phases over their median (path,
/// ms over).
pub type SlowFrame = (usize, f64, Vec<(String, f64)>);

/// The derived row: `update` less the copies of new geometry.
const LESS_COPIES: &str = "less geometry copies";

/// No path (a root span's parent).
const NO_PATH: u32 = u32::MAX;
/// `ProfileData::update_of` of a path outside every `update` whose name says it is one
/// (the fly-through's `world_update` and what runs in it): sampled at each `update`'s close.
const OUTSIDE: u32 = u32::MAX - 1;

/// What the layer gathered (shared with its owner). Paths are interned: a span carries its
/// path's index, and a frame's times are added into vectors by index (a path string and two
/// ordered-map lookups a span cost about 0.3 ms of a 1 ms `update` on the H200 host).
#[derive(Debug, Default)]
pub struct ProfileData {
    /// Per path index: the path (`policy[managed];update;schedule`).
    paths: Vec<String>,
    /// Per path: the index of the `update` path it is under (itself for an `update`;
    /// `OUTSIDE` for a path beside them that names an update; `None`: not sampled).
    update_of: Vec<Option<u32>>,
    /// Per path: one inclusive time (ms) per closed `update` under that policy.
    samples: Vec<Vec<f64>>,
    /// Per path: the running frame's inclusive time (ms), and whether it ran since its last
    /// sample.
    frame: Vec<f64>,
    ran: Vec<bool>,
    /// Per path: total self time (µs), for the folded stacks.
    self_us: Vec<f64>,
    /// (parent path, span name) -> path index.
    ids: HashMap<(u32, &'static str), u32>,
    /// A `policy` span's path (its name field in it) -> path index.
    named: HashMap<String, u32>,
}

impl ProfileData {
    /// The index of `path` (`parent`'s path, then `name`), made on first use.
    fn intern(&mut self, parent: u32, name: &'static str) -> u32 {
        if let Some(&i) = self.ids.get(&(parent, name)) {
            return i;
        }
        let path = match self.paths.get(parent as usize) {
            Some(p) => format!("{p};{name}"),
            None => name.to_string(),
        };
        let i = self.push_path(path, parent, name == "update");
        self.ids.insert((parent, name), i);
        i
    }

    /// The index of a `policy` span's path (named by its field) under `parent`.
    fn intern_named(&mut self, parent: u32, name: String) -> u32 {
        let path = match self.paths.get(parent as usize) {
            Some(p) => format!("{p};{name}"),
            None => name,
        };
        if let Some(&i) = self.named.get(&path) {
            return i;
        }
        let i = self.push_path(path.clone(), parent, false);
        self.named.insert(path, i);
        i
    }

    fn push_path(&mut self, path: String, parent: u32, is_update: bool) -> u32 {
        let i = self.paths.len() as u32;
        let under = match self.update_of.get(parent as usize).copied().flatten() {
            None if path.contains("update") => Some(OUTSIDE),
            under => under,
        };
        self.paths.push(path);
        self.update_of.push(if is_update { Some(i) } else { under });
        self.samples.push(Vec::new());
        self.frame.push(0.0);
        self.ran.push(false);
        self.self_us.push(0.0);
        i
    }

    /// An `update` (path `u`) closed: one sample per path under it, the frame's time or 0
    /// when it did not run this frame (policies update one after another), and the derived
    /// row without the copies of new geometry (the backend's `upload_geometry` spans).
    fn close_update(&mut self, u: u32) {
        let copies: f64 = (0..self.paths.len())
            .filter(|&i| {
                self.update_of[i] == Some(u) && self.paths[i].ends_with(";upload_geometry")
            })
            .map(|i| self.frame[i])
            .sum();
        let less = self.intern(u, LESS_COPIES);
        self.frame[less as usize] = self.frame[u as usize] - copies;
        // Paths beside the updates are sampled at the first `update` to close after they ran.
        let n = self.samples[u as usize].len();
        for i in 0..self.paths.len() {
            let sampled = match self.update_of[i] {
                Some(x) if x == u => true,
                Some(OUTSIDE) => self.ran[i],
                _ => false,
            };
            if sampled {
                let v = &mut self.samples[i];
                v.resize(n, 0.0);
                v.push(std::mem::take(&mut self.frame[i]));
                self.ran[i] = false;
            }
        }
    }

    /// Per path with samples, in path order.
    fn sampled(&self) -> BTreeMap<&str, &Vec<f64>> {
        self.paths
            .iter()
            .zip(&self.samples)
            .filter(|(_, v)| !v.is_empty())
            .map(|(p, v)| (p.as_str(), v))
            .collect()
    }
}

/// The layer; clone the handle from [`PhaseProfile::data`] before installing it.
#[derive(Debug, Clone, Default)]
pub struct PhaseProfile {
    data: Arc<Mutex<ProfileData>>,
}

struct Timing {
    path: u32,
    entered: Option<Instant>,
    busy: Duration,
    children: Duration,
}

/// Reads the `name` field of a `policy` span.
struct NameField(Option<String>);

impl tracing::field::Visit for NameField {
    fn record_str(&mut self, field: &tracing::field::Field, value: &str) {
        if field.name() == "name" {
            self.0 = Some(value.to_string());
        }
    }
    fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
        if field.name() == "name" {
            self.0 = Some(format!("{value:?}"));
        }
    }
}

impl PhaseProfile {
    /// A new layer.
    pub fn new() -> Self {
        Self::default()
    }

    /// The gathered data, shared.
    pub fn data(&self) -> Arc<Mutex<ProfileData>> {
        self.data.clone()
    }
}

impl<S> Layer<S> for PhaseProfile
where
    S: Subscriber + for<'a> LookupSpan<'a>,
{
    fn on_new_span(&self, attrs: &Attributes<'_>, id: &Id, ctx: Context<'_, S>) {
        let Some(span) = ctx.span(id) else { return };
        let name = span.name();
        let parent = span
            .parent()
            .and_then(|p| p.extensions().get::<Timing>().map(|t| t.path))
            .unwrap_or(NO_PATH);
        let path = if name == "policy" {
            let mut v = NameField(None);
            attrs.record(&mut v);
            let named =
                v.0.map_or_else(|| name.to_string(), |n| format!("policy[{n}]"));
            self.data.lock().intern_named(parent, named)
        } else {
            self.data.lock().intern(parent, name)
        };
        span.extensions_mut().insert(Timing {
            path,
            entered: None,
            busy: Duration::ZERO,
            children: Duration::ZERO,
        });
    }

    fn on_enter(&self, id: &Id, ctx: Context<'_, S>) {
        if let Some(span) = ctx.span(id) {
            if let Some(t) = span.extensions_mut().get_mut::<Timing>() {
                t.entered = Some(Instant::now());
            }
        }
    }

    fn on_exit(&self, id: &Id, ctx: Context<'_, S>) {
        if let Some(span) = ctx.span(id) {
            if let Some(t) = span.extensions_mut().get_mut::<Timing>() {
                if let Some(at) = t.entered.take() {
                    t.busy += at.elapsed();
                }
            }
        }
    }

    fn on_close(&self, id: Id, ctx: Context<'_, S>) {
        let Some(span) = ctx.span(&id) else { return };
        let Some((path, busy, children)) = span
            .extensions()
            .get::<Timing>()
            .map(|t| (t.path, t.busy, t.children))
        else {
            return;
        };
        if let Some(parent) = span.parent() {
            if let Some(t) = parent.extensions_mut().get_mut::<Timing>() {
                t.children += busy;
            }
        }
        let mut d = self.data.lock();
        // Only what runs inside an `update` is sampled (a `policy` span only names it).
        let Some(u) = d.update_of[path as usize] else {
            return;
        };
        let i = path as usize;
        d.frame[i] += busy.as_secs_f64() * 1e3;
        d.ran[i] = true;
        d.self_us[i] += busy.saturating_sub(children).as_secs_f64() * 1e6;
        if u == path {
            d.close_update(u);
        }
    }
}

impl ProfileData {
    /// Per path: (p50, p99, mean) in ms over the frames, in path order.
    pub fn table(&self) -> Vec<(String, f64, f64, f64)> {
        self.sampled()
            .into_iter()
            .map(|(p, v)| {
                let s = rtstream_stats::Samples::new(v.iter().copied());
                (p.to_string(), s.median(), s.percentile(0.99), s.mean())
            })
            .collect()
    }

    /// The folded stacks (path, self time in whole µs), for `inferno-flamegraph`.
    pub fn folded(&self) -> String {
        let by_path: BTreeMap<&str, f64> = self
            .paths
            .iter()
            .zip(&self.self_us)
            .filter(|(_, us)| **us >= 1.0)
            .map(|(p, us)| (p.as_str(), *us))
            .collect();
        by_path
            .into_iter()
            .map(|(p, us)| format!("{p} {}\n", us.round() as u64))
            .collect()
    }

    /// Per frame, each phase's inclusive time (ms): a header row of the paths, then one row
    /// per sample (the `n`-th `update` of each policy), for finding what makes the slowest
    /// frames slow. Only paths at most `depth` spans below the policy are written.
    pub fn frames_csv(&self, depth: usize) -> String {
        let cols: Vec<(&str, &Vec<f64>)> = self
            .sampled()
            .into_iter()
            .filter(|(p, _)| p.matches(';').count() <= depth)
            .collect();
        let rows = cols.iter().map(|(_, v)| v.len()).max().unwrap_or(0);
        let mut out = String::from("sample");
        for (p, _) in &cols {
            out.push(',');
            out.push_str(p);
        }
        out.push('\n');
        for i in 0..rows {
            out.push_str(&i.to_string());
            for (_, v) in &cols {
                out.push(',');
                if let Some(ms) = v.get(i) {
                    out.push_str(&format!("{ms:.4}"));
                }
            }
            out.push('\n');
        }
        out
    }

    /// The `n` slowest samples of `update` from sample `skip` on, each with the phases (at
    /// most `depth` spans below the policy) that took at least `min_ms` more than their median:
    /// (sample, `update` ms, [(path, ms over the median)]).
    pub fn slowest(&self, n: usize, skip: usize, depth: usize, min_ms: f64) -> Vec<SlowFrame> {
        let sampled = self.sampled();
        let Some((root, total)) = sampled
            .iter()
            .find(|(p, _)| p.ends_with("update") && !p.contains(";update;"))
            .map(|(p, v)| (*p, *v))
        else {
            return Vec::new();
        };
        let medians: Vec<(&str, &Vec<f64>, f64)> = sampled
            .iter()
            .map(|(p, v)| (*p, *v))
            .filter(|(p, _)| p.starts_with(root) && *p != root)
            .filter(|(p, _)| p.matches(';').count() <= depth && !p.ends_with(LESS_COPIES))
            .map(|(p, v)| {
                let m = rtstream_stats::Samples::new(v.iter().skip(skip).copied()).median();
                (p, v, m)
            })
            .collect();
        let mut order: Vec<usize> = (skip..total.len()).collect();
        order.sort_by(|&a, &b| total[b].total_cmp(&total[a]));
        order
            .into_iter()
            .take(n)
            .map(|i| {
                let over = medians
                    .iter()
                    .filter_map(|(p, v, m)| {
                        let d = v.get(i).copied().unwrap_or(0.0) - m;
                        let name = p.trim_start_matches(root).trim_start_matches(';');
                        (d >= min_ms).then(|| (name.to_string(), d))
                    })
                    .collect();
                (i, total[i], over)
            })
            .collect()
    }

    /// Prints the per-phase table (indented by depth).
    pub fn print(&self) {
        println!(
            "where update spends its time (per frame, ms; tracing spans, inclusive):\n{:<48} {:>8} {:>8} {:>8}",
            "phase", "p50", "p99", "mean"
        );
        let mut last_root = String::new();
        for (p, p50, p99, mean) in self.table() {
            let depth = p.matches(';').count();
            // The first level is the policy (or nothing): show it whole.
            let name = if depth == 0 {
                p.as_str()
            } else {
                p.rsplit(';').next().unwrap_or(&p)
            };
            let root = p.split(';').next().unwrap_or_default();
            if depth > 0 && root != last_root {
                println!("{root}");
                last_root = root.to_string();
            }
            println!(
                "{:<48} {:>8.3} {:>8.3} {:>8.3}",
                format!("{}{}", "  ".repeat(depth), name),
                p50,
                p99,
                mean
            );
        }
    }
}

//! The world-preset arguments shared by the streaming crate's examples (`bake_world`,
//! `format_load`): the preset names and `--asset-dir`. (The facade's examples share
//! `examples/support/cli.rs`, which needs the facade; this crate's examples cannot use it, so
//! `cli.rs` includes this file for its `AssetArgs` instead.)
//! Included with `#[path = "support/world_args.rs"] mod world_args;`.

use std::path::PathBuf;

use clap::Args;
use rtstream_streaming::WorldPreset;

/// `default`, `large` or `small:N` (an N x N corner of the default map) as a preset.
pub fn parse_preset(s: &str) -> Result<WorldPreset, String> {
    match s {
        "default" => Ok(WorldPreset::default_world()),
        "large" => Ok(WorldPreset::large_world()),
        s => match s.strip_prefix("small:").and_then(|n| n.parse().ok()) {
            Some(n) => Ok(WorldPreset::small(n, 1)),
            None => Err(format!("unknown preset {s:?} (default, large, small:N)")),
        },
    }
}

/// `--asset-dir`.
#[derive(Debug, Clone, Default, Args)]
pub struct AssetArgs {
    /// Directory of Debian's assimp-testmodels glTF2 models the world generator places
    /// (default: `RTSTREAM_ASSETS` when set, the directory the full-world evaluation loads
    /// its models from too, else the preset's, /usr/share/assimp/models/glTF2).
    #[arg(long, value_name = "DIR", env = "RTSTREAM_ASSETS")]
    pub asset_dir: Option<PathBuf>,
}

impl AssetArgs {
    /// Sets `preset`'s asset directory when `--asset-dir` was given.
    pub fn apply(&self, preset: &mut WorldPreset) {
        if let Some(dir) = &self.asset_dir {
            preset.asset_dir = dir.clone();
        }
    }
}

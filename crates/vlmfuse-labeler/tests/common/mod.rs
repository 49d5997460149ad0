#![allow(dead_code)]
//! Shared test helpers: asset lookup with an explicit, never-silent skip.

use vlmfuse_testkit::assets::{ensure_assets, AssetPaths, AssetsUnavailable};

/// The fetched assets, running the fetch script when they are missing. Returns `None` (after
/// saying why on stderr) only when the registry cannot be reached; any other problem fails the
/// test.
pub fn assets() -> Option<AssetPaths> {
    match ensure_assets() {
        Ok(a) => Some(a),
        Err(AssetsUnavailable::RegistryUnreachable(reason)) => {
            eprintln!("SKIPPED: model assets unavailable, registry unreachable: {reason}");
            None
        }
        Err(e) => panic!("{e}"),
    }
}

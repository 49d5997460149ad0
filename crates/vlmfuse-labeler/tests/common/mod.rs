#![allow(dead_code)]
//! Shared test helpers: the asset lookup of the tests marked
//! `#[ignore = "needs assets: scripts/fetch-assets.sh"]`.

use vlmfuse_testkit_models::assets::AssetPaths;

/// The fetched assets; panics, naming the fetch script, when they are missing (the test command
/// fetches them, then runs the ignored tests with `--include-ignored`).
pub fn assets() -> AssetPaths {
    vlmfuse_testkit_models::assets::require_assets()
}

#![allow(dead_code)]
//! Shared test helpers: asset lookup with an explicit, never-silent skip.

use vlmfuse_testkit::assets::AssetPaths;

/// The fetched assets, running the fetch script when they are missing. Returns `None` (after
/// saying why on stderr) only when the registry cannot be reached; any other problem fails the
/// test.
pub fn assets() -> Option<AssetPaths> {
    vlmfuse_testkit::assets::assets_or_skip("this test")
}

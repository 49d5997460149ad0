//! Where model files come from: a directory, or a Hub repo at a revision. A Hub file is read
//! from the standard HF cache when it is there (a cache `huggingface-cli download` or a copied
//! volume filled, or an earlier download); otherwise it is downloaded into that cache through
//! hf-hub, with a progress bar on the console, from `endpoint` (or `HF_ENDPOINT`, or
//! huggingface.co) — TEI's behaviour. `HF_HUB_OFFLINE=1` turns downloads off, for deployments
//! with no route to the Hub; a file that is neither cached nor downloadable is an error naming
//! the repo, revision, file, the cache searched and why the download failed.

use std::path::{Path, PathBuf};

use candle_core::{DType, Device};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

use crate::ModelError;

/// A model's file set: a plain directory, or a Hub repo at a revision inside the local HF cache.
///
/// In TOML: `{ path = "/models/clip" }` or `{ hub = "openai/clip-vit-base-patch32",
/// revision = "main" }` (`cache_dir` optional, otherwise the HF environment variables decide;
/// `endpoint` optional, a mirror, otherwise `HF_ENDPOINT` or https://huggingface.co).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum WeightSource {
    Local {
        path: PathBuf,
    },
    Hub {
        hub: String,
        #[serde(default = "main_rev")]
        revision: String,
        #[serde(default)]
        cache_dir: Option<PathBuf>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        endpoint: Option<String>,
        /// Never download (the cache only), as `HF_HUB_OFFLINE=1` does for every source.
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        offline: bool,
    },
}

fn main_rev() -> String {
    "main".into()
}

impl WeightSource {
    pub fn local(path: impl Into<PathBuf>) -> Self {
        WeightSource::Local { path: path.into() }
    }

    pub fn hub(repo: impl Into<String>, revision: impl Into<String>) -> Self {
        WeightSource::Hub {
            hub: repo.into(),
            revision: revision.into(),
            cache_dir: None,
            endpoint: None,
            offline: false,
        }
    }

    /// Reads the cache only, never downloads (tests, air-gapped deployments).
    pub fn offline(self) -> Self {
        match self {
            WeightSource::Hub {
                hub,
                revision,
                cache_dir,
                endpoint,
                ..
            } => WeightSource::Hub {
                hub,
                revision,
                cache_dir,
                endpoint,
                offline: true,
            },
            other => other,
        }
    }

    /// Downloads from this Hub endpoint (a mirror, or a test's fake hub) instead of
    /// `HF_ENDPOINT` / huggingface.co.
    pub fn with_endpoint(self, url: impl Into<String>) -> Self {
        match self {
            WeightSource::Hub {
                hub,
                revision,
                cache_dir,
                offline,
                ..
            } => WeightSource::Hub {
                hub,
                revision,
                cache_dir,
                endpoint: Some(url.into()),
                offline,
            },
            other => other,
        }
    }

    /// Pins the cache root, for tests and for deployments that mount the cache somewhere the
    /// environment does not describe.
    pub fn with_cache_dir(self, dir: impl Into<PathBuf>) -> Self {
        match self {
            WeightSource::Hub {
                hub,
                revision,
                endpoint,
                offline,
                ..
            } => WeightSource::Hub {
                hub,
                revision,
                cache_dir: Some(dir.into()),
                endpoint,
                offline,
            },
            other => other,
        }
    }

    /// Accepts the short CLI form: `hf:org/name[@revision]`, anything else is a directory.
    pub fn parse(s: &str) -> Self {
        match s.strip_prefix("hf:").or_else(|| s.strip_prefix("hf://")) {
            Some(rest) => {
                let (repo, rev) = rest.split_once('@').unwrap_or((rest, "main"));
                WeightSource::hub(repo, rev)
            }
            None => WeightSource::local(s),
        }
    }

    /// Human-readable origin for logs and `/readyz`.
    pub fn describe(&self) -> String {
        match self {
            WeightSource::Local { path } => path.display().to_string(),
            WeightSource::Hub { hub, revision, .. } => format!("hf:{hub}@{revision}"),
        }
    }

    /// Path of `file`, or [`ModelError::MissingWeights`] naming every place looked at.
    pub fn resolve(&self, file: &str) -> Result<PathBuf, ModelError> {
        match self.try_resolve(file, false)? {
            Ok(p) => Ok(p),
            Err(searched) => Err(ModelError::MissingWeights {
                file: file.to_string(),
                searched,
            }),
        }
    }

    /// Like [`resolve`](Self::resolve) for files that may legitimately be absent
    /// (`model.safetensors.index.json`, `preprocessor_config.json`).
    pub fn resolve_optional(&self, file: &str) -> Result<Option<PathBuf>, ModelError> {
        Ok(self.try_resolve(file, true)?.ok())
    }

    /// Outer error: the source itself is unusable (unknown revision, no such directory).
    /// Inner error: the source is fine but lacks `file`; carries the places searched.
    /// `optional`: the file may legitimately be absent from the repo, so a download that cannot
    /// be made (no route to the Hub) leaves it absent, with a warning, where a cached snapshot
    /// exists; a required file is an error then.
    fn try_resolve(
        &self,
        file: &str,
        optional: bool,
    ) -> Result<Result<PathBuf, Vec<PathBuf>>, ModelError> {
        match self {
            WeightSource::Local { path } => {
                if !path.is_dir() {
                    return Err(ModelError::MissingWeights {
                        file: file.to_string(),
                        searched: vec![path.clone()],
                    });
                }
                let p = path.join(file);
                Ok(if p.is_file() { Ok(p) } else { Err(vec![p]) })
            }
            WeightSource::Hub {
                hub,
                revision,
                cache_dir,
                endpoint,
                offline,
            } => {
                let root = match cache_dir {
                    Some(d) => d.clone(),
                    None => hub_cache_dir(),
                };
                // The cache first: a deployment without a route to the Hub works from it.
                let snapshot = resolve_snapshot(&root, hub, revision);
                if let Ok(snap) = &snapshot {
                    let p = snap.join(file);
                    // Snapshot entries are symlinks into blobs/; `is_file` follows them, so a
                    // dangling link (blob deleted) counts as missing.
                    if p.is_file() {
                        return Ok(Ok(p));
                    }
                    // Known to be absent from the repo (a 404 recorded, as huggingface_hub does).
                    let commit = snap.file_name().and_then(|c| c.to_str());
                    if commit.is_some_and(|c| no_exist_marker(&root, hub, c, file).is_file()) {
                        return Ok(Err(vec![p]));
                    }
                }
                let have_snapshot = snapshot.is_ok();
                let cached = snapshot.map(|snap| Err(vec![snap.join(file)]));
                if *offline || offline_from(|k| std::env::var(k).ok()) {
                    return cached;
                }
                match download(&root, hub, revision, endpoint.as_deref(), file) {
                    Ok(p) => Ok(Ok(p)),
                    // The repo has no such file: as missing as an absent cached one (optional
                    // files such as `model.safetensors.index.json` are looked up this way).
                    Err(Download::NotInRepo { url, commit }) => {
                        if let Some(c) = commit {
                            let m = no_exist_marker(&root, hub, &c, file);
                            if let Some(dir) = m.parent() {
                                let _ = std::fs::create_dir_all(dir);
                            }
                            let _ = std::fs::write(&m, b"");
                        }
                        Ok(Err(vec![PathBuf::from(url)]))
                    }
                    Err(Download::Failed(reason)) if optional && have_snapshot => {
                        tracing::warn!(
                            repo = %hub, %revision, file, %reason,
                            "could not ask the Hub for an optional file the cached snapshot lacks; going on without it"
                        );
                        cached
                    }
                    Err(Download::Failed(reason)) => Err(ModelError::Download(Box::new(
                        crate::error::DownloadFailure {
                            repo: hub.clone(),
                            revision: revision.clone(),
                            file: file.to_string(),
                            cache: root,
                            reason,
                        },
                    ))),
                }
            }
        }
    }

    /// The safetensors files of the model: `model.safetensors`, or the shards listed by
    /// `model.safetensors.index.json`.
    pub fn safetensors_files(&self) -> Result<Vec<PathBuf>, ModelError> {
        if let Some(index) = self.resolve_optional("model.safetensors.index.json")? {
            let text = read_to_string(&index)?;
            let v: serde_json::Value =
                serde_json::from_str(&text).map_err(|e| ModelError::BadWeights {
                    path: index.clone(),
                    reason: e.to_string(),
                })?;
            let map = v
                .get("weight_map")
                .and_then(|m| m.as_object())
                .ok_or_else(|| ModelError::BadWeights {
                    path: index.clone(),
                    reason: "no `weight_map` object".into(),
                })?;
            let mut shards: Vec<String> = map
                .values()
                .filter_map(|s| s.as_str().map(str::to_string))
                .collect();
            shards.sort();
            shards.dedup();
            return shards.iter().map(|s| self.resolve(s)).collect();
        }
        Ok(vec![self.resolve("model.safetensors")?])
    }

    /// Reads and parses a JSON file of the model (config.json etc.).
    pub fn read_json<T: serde::de::DeserializeOwned>(&self, file: &str) -> Result<T, ModelError> {
        let p = self.resolve(file)?;
        let text = read_to_string(&p)?;
        serde_json::from_str(&text)
            .map_err(|e| ModelError::BadConfig(format!("{}: {e}", p.display())))
    }
}

fn read_to_string(p: &Path) -> Result<String, ModelError> {
    std::fs::read_to_string(p).map_err(|source| ModelError::Io {
        path: p.to_path_buf(),
        source,
    })
}

/// Whether downloads are off: `HF_HUB_OFFLINE` set to a true value, as `huggingface_hub` reads it.
fn offline_from(var: impl Fn(&str) -> Option<String>) -> bool {
    var("HF_HUB_OFFLINE").is_some_and(|v| {
        matches!(
            v.trim().to_ascii_lowercase().as_str(),
            "1" | "true" | "yes" | "on"
        )
    })
}

enum Download {
    /// The Hub answered 404 for the file: its URL, and the revision's commit when the Hub said.
    NotInRepo {
        url: String,
        commit: Option<String>,
    },
    Failed(String),
}

fn repo_folder(repo_id: &str) -> String {
    hf_hub::Repo::new(repo_id.to_string(), hf_hub::RepoType::Model).folder_name()
}

/// `<repo>/.no_exist/<commit>/<file>`: huggingface_hub's record that a revision has no such
/// file, so that a later load does not ask again.
fn no_exist_marker(root: &Path, repo_id: &str, commit: &str, file: &str) -> PathBuf {
    root.join(repo_folder(repo_id))
        .join(".no_exist")
        .join(commit)
        .join(file)
}

/// Downloads one file of `repo_id@revision` into the cache under `root` (hf-hub's layout:
/// blobs, snapshots, refs), with a progress bar when stderr is a terminal.
fn download(
    root: &Path,
    repo_id: &str,
    revision: &str,
    endpoint: Option<&str>,
    file: &str,
) -> Result<PathBuf, Download> {
    use std::io::IsTerminal;
    let mut b = hf_hub::api::sync::ApiBuilder::from_env()
        .with_cache_dir(root.to_path_buf())
        .with_progress(std::io::stderr().is_terminal())
        .with_retries(2);
    if let Some(url) = endpoint {
        b = b.with_endpoint(url.trim_end_matches('/').to_string());
    }
    if let Ok(token) = std::env::var("HF_TOKEN") {
        if !token.trim().is_empty() {
            b = b.with_token(Some(token.trim().to_string()));
        }
    }
    let api = b
        .build()
        .map_err(|e| Download::Failed(format!("cannot set up the Hub client: {e}")))?;
    let repo = api.repo(hf_hub::Repo::with_revision(
        repo_id.to_string(),
        hf_hub::RepoType::Model,
        revision.to_string(),
    ));
    let url = repo.url(file);
    tracing::info!(%url, cache = %root.display(), "downloading a model file from the Hub");
    repo.download(file).map_err(|e| {
        let not_found = match &e {
            hf_hub::api::sync::ApiError::RequestError(r) => {
                matches!(**r, ureq::Error::StatusCode(404))
            }
            _ => false,
        };
        if not_found {
            // The commit of the revision, if the cache knows it (a 404 answer carries none).
            let commit = std::fs::read_to_string(
                root.join(repo_folder(repo_id)).join("refs").join(revision),
            )
            .ok()
            .map(|c| c.trim().to_string())
            .or_else(|| {
                (revision.len() == 40 && revision.bytes().all(|b| b.is_ascii_hexdigit()))
                    .then(|| revision.to_string())
            });
            Download::NotInRepo {
                url: url.clone(),
                commit,
            }
        } else {
            Download::Failed(format!("{url}: {e}"))
        }
    })
}

/// The HF hub cache root from the process environment.
pub fn hub_cache_dir() -> PathBuf {
    hub_cache_dir_from(|k| std::env::var(k).ok())
}

/// Same rules as `huggingface_hub`: `HF_HUB_CACHE`, else `$HF_HOME/hub`, else
/// `$XDG_CACHE_HOME/huggingface/hub`, else `~/.cache/huggingface/hub`. Takes the lookup as a
/// function so tests need not mutate the (process-global, racy) environment. hf-hub 0.5's own
/// `Cache::from_env` ignores `HF_HUB_CACHE` and `XDG_CACHE_HOME`, hence this.
pub fn hub_cache_dir_from(env: impl Fn(&str) -> Option<String>) -> PathBuf {
    let non_empty = |k: &str| env(k).filter(|v| !v.is_empty());
    if let Some(d) = non_empty("HF_HUB_CACHE").or_else(|| non_empty("HUGGINGFACE_HUB_CACHE")) {
        return PathBuf::from(d);
    }
    if let Some(h) = non_empty("HF_HOME") {
        return PathBuf::from(h).join("hub");
    }
    if let Some(x) = non_empty("XDG_CACHE_HOME") {
        return PathBuf::from(x).join("huggingface").join("hub");
    }
    let home = non_empty("HOME").unwrap_or_else(|| ".".into());
    PathBuf::from(home)
        .join(".cache")
        .join("huggingface")
        .join("hub")
}

/// `<root>/models--org--name/snapshots/<commit>` for a branch/tag (via `refs/<rev>`) or a commit
/// hash (directly). hf-hub 0.5's `CacheRepo::get` only handles the former and does not trim the
/// ref file, so resolution is done here with its layout helpers.
fn resolve_snapshot(root: &Path, repo_id: &str, revision: &str) -> Result<PathBuf, ModelError> {
    let repo = hf_hub::Repo::with_revision(
        repo_id.to_string(),
        hf_hub::RepoType::Model,
        revision.to_string(),
    );
    let cache_repo = hf_hub::Cache::new(root.to_path_buf()).repo(repo.clone());
    let repo_dir = root.join(repo.folder_name());
    // `revision` may contain '/' (e.g. "refs/pr/15"); joining keeps it as sub-directories,
    // exactly how huggingface_hub writes it.
    let ref_file = repo_dir.join("refs").join(revision);
    if let Ok(commit) = std::fs::read_to_string(&ref_file) {
        let commit = commit.trim();
        let snap = cache_repo.pointer_path(commit);
        if snap.is_dir() {
            return Ok(snap);
        }
        return Err(ModelError::MissingWeights {
            file: format!("snapshot {commit} (from ref `{revision}`)"),
            searched: vec![snap],
        });
    }
    let direct = cache_repo.pointer_path(revision);
    if direct.is_dir() {
        return Ok(direct);
    }
    Err(ModelError::MissingWeights {
        file: format!("revision `{revision}` of {repo_id} (offline cache; downloads are disabled)"),
        searched: vec![ref_file, direct],
    })
}

/// Memory-maps safetensors files into a [`VarBuilder`], turning a truncated/corrupt file into an
/// error that names it (candle's own message does not say which shard).
pub fn var_builder(
    files: &[PathBuf],
    dtype: DType,
    device: &Device,
) -> Result<VarBuilder<'static>, ModelError> {
    for f in files {
        // Parse each header up front: `from_mmaped_safetensors` would fail too, but without the
        // path, and only for the first bad shard.
        // SAFETY: read-only mapping, dropped right away; model files are not expected to change
        // while the service loads them.
        if let Err(e) = unsafe { candle_core::safetensors::MmapedSafetensors::new(f) } {
            return Err(ModelError::BadWeights {
                path: f.clone(),
                reason: e.to_string(),
            });
        }
    }
    // SAFETY: as above; the VarBuilder keeps the mapping alive for the model's lifetime.
    unsafe { VarBuilder::from_mmaped_safetensors(files, dtype, device) }.map_err(|e| {
        ModelError::BadWeights {
            path: files.first().cloned().unwrap_or_default(),
            reason: e.to_string(),
        }
    })
}

/// A PyTorch state dict (`torch.save`'s `.bin` / `.pth`), under `key` when it is nested
/// (`{"model": state_dict}`), on the CPU; a broken file names itself.
pub fn read_pth(
    path: &Path,
    key: Option<&str>,
) -> Result<std::collections::HashMap<String, candle_core::Tensor>, ModelError> {
    candle_core::pickle::read_all_with_key(path, key)
        .map(|v| v.into_iter().collect())
        .map_err(|e| ModelError::BadWeights {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(p: &Path, s: &str) {
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, s).unwrap();
    }

    #[test]
    fn cache_dir_env_precedence() {
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(kk, _)| *kk == k)
                    .map(|(_, v)| v.to_string())
            }
        };
        assert_eq!(
            hub_cache_dir_from(env(&[("HF_HUB_CACHE", "/c"), ("HF_HOME", "/h")])),
            PathBuf::from("/c")
        );
        assert_eq!(
            hub_cache_dir_from(env(&[("HF_HOME", "/h"), ("XDG_CACHE_HOME", "/x")])),
            PathBuf::from("/h/hub")
        );
        assert_eq!(
            hub_cache_dir_from(env(&[("XDG_CACHE_HOME", "/x"), ("HOME", "/u")])),
            PathBuf::from("/x/huggingface/hub")
        );
        assert_eq!(
            hub_cache_dir_from(env(&[("HOME", "/u")])),
            PathBuf::from("/u/.cache/huggingface/hub")
        );
        assert_eq!(
            hub_cache_dir_from(env(&[("HF_HUB_CACHE", ""), ("HOME", "/u")])),
            PathBuf::from("/u/.cache/huggingface/hub")
        );
    }

    #[test]
    fn hub_resolves_branch_commit_and_pr_refs() {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path();
        let repo = root.join("models--org--tiny");
        let commit = "0123456789abcdef0123456789abcdef01234567";
        write(&repo.join("refs/main"), &format!("{commit}\n"));
        write(&repo.join("refs/refs/pr/15"), commit);
        write(
            &repo.join("snapshots").join(commit).join("config.json"),
            "{}",
        );

        for rev in ["main", "refs/pr/15", commit] {
            let src = WeightSource::hub("org/tiny", rev)
                .with_cache_dir(root)
                .offline();
            let p = src.resolve("config.json").unwrap();
            assert_eq!(
                p,
                repo.join("snapshots").join(commit).join("config.json"),
                "{rev}"
            );
        }

        let src = WeightSource::hub("org/tiny", "main")
            .with_cache_dir(root)
            .offline();
        let e = src.resolve("model.safetensors").unwrap_err();
        let msg = e.to_string();
        assert_eq!(e.kind(), "missing_weights");
        assert!(
            msg.contains("model.safetensors") && msg.contains(commit),
            "{msg}"
        );
        assert_eq!(src.resolve_optional("nope.json").unwrap(), None);

        let e = WeightSource::hub("org/tiny", "v2")
            .with_cache_dir(root)
            .offline()
            .resolve("config.json")
            .unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("`v2`") && msg.contains("refs/v2"), "{msg}");
        let e = WeightSource::hub("org/other", "main")
            .with_cache_dir(root)
            .offline()
            .resolve("config.json")
            .unwrap_err();
        assert!(e.to_string().contains("models--org--other"), "{e}");
    }

    #[test]
    fn local_dir_and_parse() {
        let tmp = tempfile::tempdir().unwrap();
        write(&tmp.path().join("config.json"), "{\"a\":1}");
        let src = WeightSource::local(tmp.path());
        let v: serde_json::Value = src.read_json("config.json").unwrap();
        assert_eq!(v["a"], 1);
        let e = src.resolve("model.safetensors").unwrap_err();
        assert!(e
            .to_string()
            .contains(&tmp.path().join("model.safetensors").display().to_string()));
        let e = WeightSource::local("/definitely/not/here")
            .resolve("config.json")
            .unwrap_err();
        assert!(e.to_string().contains("/definitely/not/here"));

        assert_eq!(
            WeightSource::parse("hf:a/b@v1"),
            WeightSource::hub("a/b", "v1")
        );
        assert_eq!(
            WeightSource::parse("hf:a/b"),
            WeightSource::hub("a/b", "main")
        );
        assert_eq!(WeightSource::parse("/m/x"), WeightSource::local("/m/x"));
    }

    #[test]
    fn sharded_index_lists_each_shard_once() {
        let tmp = tempfile::tempdir().unwrap();
        write(
            &tmp.path().join("model.safetensors.index.json"),
            r#"{"weight_map":{"a":"m-2.safetensors","b":"m-1.safetensors","c":"m-2.safetensors"}}"#,
        );
        write(&tmp.path().join("m-1.safetensors"), "");
        let src = WeightSource::local(tmp.path());
        // m-2 is missing: the error must name it.
        let e = src.safetensors_files().unwrap_err();
        assert!(e.to_string().contains("m-2.safetensors"), "{e}");
        write(&tmp.path().join("m-2.safetensors"), "");
        let files = src.safetensors_files().unwrap();
        assert_eq!(files.len(), 2);
        assert!(files[0].ends_with("m-1.safetensors"));
    }

    #[test]
    fn serde_forms() {
        let a: WeightSource = serde_json::from_str(r#"{"path":"/m"}"#).unwrap();
        assert_eq!(a, WeightSource::local("/m"));
        let b: WeightSource = serde_json::from_str(r#"{"hub":"o/n"}"#).unwrap();
        assert_eq!(b, WeightSource::hub("o/n", "main"));
    }

    #[test]
    fn corrupt_safetensors_is_named() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("model.safetensors");
        std::fs::write(&p, b"\x10\x00\x00\x00\x00\x00\x00\x00{not json").unwrap();
        let e = match var_builder(std::slice::from_ref(&p), DType::F32, &Device::Cpu) {
            Err(e) => e,
            Ok(_) => panic!("corrupt file accepted"),
        };
        assert_eq!(e.kind(), "bad_weights");
        assert!(e.to_string().contains(&p.display().to_string()), "{e}");
    }
}

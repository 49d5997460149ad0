//! Loading the real library from the asset cache and running a session (one process: ONNX
//! Runtime allows one environment per process, so each test file here is its own scenario).

use std::path::Path;

use vlmfuse_ort::ort::value::TensorRef;
use vlmfuse_ort::{cached_library, environment, loaded_library, session_from_file, SessionOptions};

fn model() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/onnx/tiny-bert/model.onnx")
}

/// The library where `scripts/fetch-assets.sh` puts it (under `$VLMFUSE_ASSETS`, else
/// `~/.cache/vlmfuse-assets`); a panic naming the script when it is not there.
fn fetched_library() -> std::path::PathBuf {
    let lib = cached_library();
    assert!(
        lib.is_file(),
        "ONNX Runtime missing at {}: run scripts/fetch-assets.sh (or ./scripts/test, which does)",
        lib.display()
    );
    lib
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn a_bad_library_is_an_error_then_the_real_one_loads_and_runs() {
    let onnxruntime = fetched_library();
    // A file that is not a shared library: an error naming it, never a panic inside `ort`.
    let dir = tempfile::tempdir().unwrap();
    let fake = dir.path().join("libonnxruntime.so");
    std::fs::write(&fake, b"not a library").unwrap();
    let e = environment(Some(&fake)).unwrap_err();
    assert_eq!(e.kind(), "runtime_load", "{e}");
    assert!(e.to_string().contains(&fake.display().to_string()), "{e}");
    assert!(loaded_library().is_none());

    // The failed attempt left nothing behind: the real library loads now.
    environment(Some(&onnxruntime)).unwrap();
    assert_eq!(loaded_library(), Some(onnxruntime.as_path()));
    // Another path later gets the loaded runtime (one per process), not an error.
    environment(Some(&fake)).unwrap();

    let opts = SessionOptions {
        threads: Some(2),
        library: Some(onnxruntime.clone()),
    };
    let mut s = session_from_file(&model(), &opts).unwrap();
    let names: Vec<&str> = s.inputs().iter().map(|o| o.name()).collect();
    assert_eq!(names, ["input_ids", "attention_mask", "token_type_ids"]);
    let ids = [2i64, 17, 3];
    let ones = [1i64; 3];
    let zeros = [0i64; 3];
    let out = s
        .run(vlmfuse_ort::ort::inputs![
            "input_ids" => TensorRef::from_array_view(([1usize, 3], &ids[..])).unwrap(),
            "attention_mask" => TensorRef::from_array_view(([1usize, 3], &ones[..])).unwrap(),
            "token_type_ids" => TensorRef::from_array_view(([1usize, 3], &zeros[..])).unwrap(),
        ])
        .unwrap();
    let (shape, data) = out["last_hidden_state"]
        .try_extract_tensor::<f32>()
        .unwrap();
    assert_eq!(&shape[..], &[1, 3, 32]);
    assert!(data.iter().all(|x| x.is_finite()));

    // A file that is not ONNX.
    let junk = dir.path().join("junk.onnx");
    std::fs::write(&junk, b"junk").unwrap();
    let e = session_from_file(&junk, &opts).unwrap_err();
    assert_eq!(e.kind(), "bad_model");
    assert!(e.to_string().contains("junk.onnx"), "{e}");
}

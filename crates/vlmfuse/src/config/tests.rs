use super::*;
use vlmfuse_models::WeightSource;
const SHIPPED: &str = include_str!("../../../../config/default.toml");

#[test]
fn the_shipped_file_equals_the_builtin_defaults() {
    let file = Config::from_toml(SHIPPED).unwrap();
    assert_eq!(file, Config::default());
}

#[test]
fn the_shipped_file_sets_every_field() {
    // Every key the defaults serialise must appear in the file, so the file documents all.
    let defaults = toml::Value::try_from(Config::default()).unwrap();
    let file: toml::Value = toml::from_str(SHIPPED).unwrap();
    fn keys(v: &toml::Value, prefix: &str, out: &mut Vec<String>) {
        if let toml::Value::Table(t) = v {
            for (k, v) in t {
                let p = format!("{prefix}{k}");
                out.push(p.clone());
                keys(v, &format!("{p}."), out);
            }
        }
    }
    let (mut a, mut b) = (Vec::new(), Vec::new());
    keys(&defaults, "", &mut a);
    keys(&file, "", &mut b);
    for k in a {
        assert!(b.contains(&k), "config/default.toml does not set {k}");
    }
}

#[test]
fn flags_override_the_file_and_typos_are_refused() {
    let args =
        ServeArgs::try_parse_from(["serve", "--listen", "127.0.0.1:9", "--reporters", "a, b"])
            .unwrap();
    let cfg = Config::load(&args).unwrap();
    assert_eq!(cfg.server.listen, "127.0.0.1:9");
    assert_eq!(cfg.reporters, vec!["a", "b"]);
    assert!(Config::from_toml("reporter = [\"a\"]").is_err());
    assert!(Config::from_toml("[fusion]\nkk = 3").is_err());
    assert!(Config::from_toml("[server]\nlisten = \"nowhere\"").is_err());
}

/// A flag replaces the file's value; a flag that is not given leaves the file's value alone
/// (it does not fall back to the built-in default).
#[test]
fn flags_layer_over_the_file_field_by_field() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("c.toml");
    std::fs::write(
        &file,
        "[limits]\nconcurrency_limit = 7\nmax_batch_rounds = 9\n\n[media]\nframes = 3\n\n\
         [embedder]\nweights = { path = \"/m\" }\n",
    )
    .unwrap();
    let f = file.to_str().unwrap();
    let args = ServeArgs::try_parse_from([
        "serve",
        "--config",
        f,
        "--max-batch-rounds",
        "2",
        "--embedder-device",
        "cuda:1",
    ])
    .unwrap();
    let cfg = Config::load(&args).unwrap();
    assert_eq!(cfg.limits.concurrency_limit, 7);
    assert_eq!(cfg.limits.max_batch_rounds, 2);
    assert_eq!(cfg.media.frames, 3);
    assert_eq!(cfg.media.max_clips, MediaConfig::default().max_clips);
    let e = cfg.embedder.unwrap();
    assert_eq!(
        (e.weights, e.device.as_str()),
        (WeightSource::local("/m"), "cuda:1")
    );
    // A bad value names the flag; an invalid combination is refused after layering.
    let e = ServeArgs::try_parse_from(["serve", "--media-frames", "x"]).unwrap_err();
    assert!(e.to_string().contains("--media-frames"), "{e}");
    let args = ServeArgs::try_parse_from(["serve", "--media-frames", "0"]).unwrap();
    assert!(Config::load(&args).is_err());
}

/// The labeler is one tagged table: a field of another kind is refused, not ignored.
#[test]
fn the_labeler_section_is_a_tagged_enum() {
    let cfg = Config::from_toml("[labeler]\nkind = \"gguf\"\nmodel_path = \"/m.gguf\"").unwrap();
    assert_eq!(
        cfg.labeler,
        LabelerConfig::Gguf(GgufLabelerConfig {
            model_path: Some("/m.gguf".into()),
            ..Default::default()
        })
    );
    assert!(Config::from_toml("[labeler]\nkind = \"gguf\"\nbase_url = \"http://x\"").is_err());
    // The GGUF labeler writes its label list: a threshold is a leftover, refused.
    assert!(Config::from_toml("[labeler]\nkind = \"gguf\"\nthreshold = 0.5").is_err());
    assert!(Config::from_toml("[labeler]\nkind = \"nope\"").is_err());
}

/// The commented examples of config/default.toml, uncommented, are a valid config.
#[test]
fn the_commented_pipeline_examples_parse() {
    let mut text = String::new();
    let mut on = false;
    for line in SHIPPED.lines() {
        if line.starts_with("# [embedder]") {
            on = true;
        }
        if line.starts_with("# Text -> labels") {
            on = false;
        }
        if on {
            if let Some(rest) = line.strip_prefix("# ") {
                let toml_line = rest.starts_with('[') || rest.contains(" = ");
                if toml_line && !rest.starts_with('#') {
                    text.push_str(rest);
                    text.push('\n');
                }
            }
        }
    }
    let text = format!("reporters = [\"vlaad\", \"videollama2\", \"videollava\"]\n{text}");
    let cfg = Config::from_toml(&text).unwrap_or_else(|e| panic!("{e}\n{text}"));
    assert_eq!(cfg.reporter.len(), 3);
    match &cfg.reporter[2].backend {
        ReporterBackend::Candle(c) => assert_eq!(c.name, "videollava"),
        other => panic!("{other:?}"),
    }
    assert_eq!(cfg.reporter[0].name(), "videollama2");
    assert_eq!(cfg.reporter[0].round_timeout_s, 180.0);
    match &cfg.reporter[1].backend {
        ReporterBackend::Candle(c) => {
            assert_eq!(c.device, "cuda:1");
            assert!(c.adapter.is_some());
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(cfg.embedder.unwrap().device, "cpu");
    // A reporter whose name is not in `reporters` is refused.
    let bad = text.replace("name = \"vlaad\"", "name = \"nobody\"");
    assert!(Config::from_toml(&bad).is_err());
}

#[test]
fn the_embedder_backend_is_chosen_in_the_file_and_typos_are_refused() {
    let cfg = Config::from_toml(
        "[embedder]\nweights = { path = \"/m/clip-onnx\" }\nbackend = \"onnx\"\nthreads = 2\n\
         model_file = \"onnx/vision_model.onnx\"\n",
    )
    .unwrap();
    let e = cfg.embedder.unwrap();
    assert_eq!(e.backend, EmbedderBackend::Onnx);
    assert_eq!(e.threads, Some(2));
    assert_eq!(e.model_file.as_deref(), Some("onnx/vision_model.onnx"));
    let cfg = Config::from_toml("[embedder]\nweights = { path = \"/m/clip\" }\n").unwrap();
    assert_eq!(cfg.embedder.unwrap().backend, EmbedderBackend::Candle);
    let err =
        Config::from_toml("[embedder]\nweights = { path = \"/m\" }\nbackend = \"tensorrt\"\n")
            .unwrap_err();
    assert!(format!("{err:#}").contains("backend"), "{err:#}");
}

/// `vlmfuse serve --config FILE` with `backend = "onnx"` in the file and no flag: the flag's
/// absence must leave the file alone (a clap default used to switch it back to candle, so an
/// ONNX deployment silently ran candle at half the speed).
#[test]
fn the_files_embedder_backend_survives_layering_without_the_flag() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("c.toml");
    std::fs::write(
        &file,
        "[embedder]\nweights = { path = \"/m\" }\nbackend = \"onnx\"\nthreads = 3\n",
    )
    .unwrap();
    let f = file.to_str().unwrap();
    let cfg = Config::load(&ServeArgs::try_parse_from(["serve", "--config", f]).unwrap()).unwrap();
    let e = cfg.embedder.unwrap();
    assert_eq!((e.backend, e.threads), (EmbedderBackend::Onnx, Some(3)));
    let args = ServeArgs::try_parse_from(["serve", "--config", f, "--embedder-backend", "candle"])
        .unwrap();
    let e = Config::load(&args).unwrap().embedder.unwrap();
    assert_eq!(e.backend, EmbedderBackend::Candle);
}

#[test]
fn durations_that_would_break_later_are_refused_with_the_field_named() {
    for (toml, field) in [
        (
            "[limits]\nrequest_timeout_s = 1e20\n",
            "limits.request_timeout_s",
        ),
        (
            "[limits]\nrequest_timeout_s = nan\n",
            "limits.request_timeout_s",
        ),
        (
            "[media]\nrequest_timeout_s = -1.0\n",
            "media.request_timeout_s",
        ),
        ("[media]\nmax_duration_s = nan\n", "media.max_duration_s"),
        (
            "[labeler]\nkind = \"openai\"\ntimeout_s = inf\n",
            "labeler.timeout_s",
        ),
    ] {
        let err = Config::from_toml(toml)
            .and_then(|c| c.validate().map(|_| c))
            .unwrap_err();
        assert!(format!("{err:#}").contains(field), "{toml}: {err:#}");
    }
}

/// `kind = "candle"` lost the old candle-transformers path's knobs: a config that still sets one
/// fails and says what decides now; a misspelt field is refused too, not ignored.
#[test]
fn the_candle_reporter_refuses_removed_and_unknown_fields() {
    let base = "reporters = [\"q\"]\n[[reporter]]\nkind = \"candle\"\nname = \"q\"\nweights = { path = \"/m\" }\n";
    let cfg = Config::from_toml(&format!(
        "{base}round_timeout_s = 5.0\nmax_new_tokens = 3\n"
    ))
    .unwrap();
    assert_eq!(cfg.reporter[0].name(), "q");
    for removed in [
        "causal_prefill = false",
        "max_pixels = 1024",
        "min_pixels = 16",
    ] {
        let e = format!(
            "{:#}",
            Config::from_toml(&format!("{base}{removed}\n")).unwrap_err()
        );
        let field = removed.split(' ').next().unwrap();
        assert!(e.contains(field), "{e}");
        assert!(e.contains("processor config"), "{e}");
    }
    let e = format!(
        "{:#}",
        Config::from_toml(&format!("{base}max_new_token = 3\n")).unwrap_err()
    );
    assert!(e.contains("max_new_token"), "{e}");
}

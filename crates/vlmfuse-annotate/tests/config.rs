//! AnnotateConfig: defaults, validation, and the TOML form the service reads.

use vlmfuse_annotate::AnnotateConfig;

#[test]
fn defaults_validate() {
    AnnotateConfig::default().validate().unwrap();
}

#[test]
fn negative_and_non_finite_thresholds_are_refused() {
    let json = serde_json::to_value(AnnotateConfig::default()).unwrap();
    let fields: Vec<String> = json.as_object().unwrap().keys().cloned().collect();
    assert!(fields.len() >= 30);
    for f in &fields {
        let mut v = json.clone();
        v[f.as_str()] = serde_json::json!(-1.0);
        let cfg: AnnotateConfig = serde_json::from_value(v).unwrap();
        let e = cfg.validate().unwrap_err();
        assert!(e.contains(f.as_str()) || e.contains("below"), "{f}: {e}");
    }
    let cfg = AnnotateConfig {
        turn_window_s: f64::NAN,
        ..AnnotateConfig::default()
    };
    assert!(cfg.validate().unwrap_err().contains("turn_window_s"));
    let cfg = AnnotateConfig {
        brake_min_s: 0.0,
        ..AnnotateConfig::default()
    };
    assert!(cfg.validate().unwrap_err().contains("brake_min_s"));
}

#[test]
fn inverted_bands_are_refused() {
    for cfg in [
        AnnotateConfig {
            brake_clear_mps2: 2.0,
            ..AnnotateConfig::default()
        },
        AnnotateConfig {
            stop_clear_mps: 0.2,
            ..AnnotateConfig::default()
        },
        AnnotateConfig {
            turn_clear_deg: 50.0,
            ..AnnotateConfig::default()
        },
        AnnotateConfig {
            merge_lateral_unsignalled_m: 2.0,
            ..AnnotateConfig::default()
        },
        AnnotateConfig {
            min_coverage: 1.5,
            ..AnnotateConfig::default()
        },
        AnnotateConfig {
            brake_pedal: 2.0,
            ..AnnotateConfig::default()
        },
    ] {
        assert!(cfg.validate().is_err(), "{cfg:?}");
    }
}

#[test]
fn unknown_fields_are_refused() {
    let e = serde_json::from_str::<AnnotateConfig>(r#"{"brake_decel": 2.0}"#).unwrap_err();
    assert!(e.to_string().contains("brake_decel"), "{e}");
    let e = toml::from_str::<AnnotateConfig>("stop_speed = 0.5\n").unwrap_err();
    assert!(e.to_string().contains("stop_speed"), "{e}");
}

#[test]
fn missing_fields_take_their_defaults() {
    let cfg: AnnotateConfig = toml::from_str("brake_decel_mps2 = 2.0\n").unwrap();
    assert_eq!(cfg.brake_decel_mps2, 2.0);
    assert_eq!(cfg.stop_speed_mps, AnnotateConfig::default().stop_speed_mps);
    let cfg: AnnotateConfig = serde_json::from_str("{}").unwrap();
    assert_eq!(cfg, AnnotateConfig::default());
}

#[test]
fn the_toml_form_round_trips_under_an_annotate_table() {
    #[derive(serde::Deserialize)]
    struct File {
        annotate: AnnotateConfig,
    }
    let body = toml::to_string(&AnnotateConfig::default()).unwrap();
    println!("[annotate]\n{body}");
    let f: File = toml::from_str(&format!("[annotate]\n{body}")).unwrap();
    assert_eq!(f.annotate, AnnotateConfig::default());
}

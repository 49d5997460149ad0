//! Track parsing and validation: both formats, missing columns, and every error kind.

use vlmfuse_annotate::sim::{scenario, Manoeuvre, SimConfig};
use vlmfuse_annotate::{Track, TrackError, TrackLimits, TurnSignal};

const CSV: &str = "\
t_s,speed_mps,accel_mps2,steering_deg,yaw_rate_dps,brake,throttle,turn_signal
0.0,10.0,0.1,2.0,0.5,0.0,0.2,none
0.1,10.0,,2.5,0.4,0.0,0.2,left
0.2,9.9,-0.2,3.0,0.3,0.1,0.0,
0.3,9.8,-0.3,-1.0,-0.2,0.3,0.0,right
";

const JSONL: &str = r#"
{"t_s": 0.0, "speed_mps": 10.0, "accel_mps2": 0.1, "steering_deg": 2.0, "yaw_rate_dps": 0.5, "brake": 0.0, "throttle": 0.2, "turn_signal": "none"}
{"t_s": 0.1, "speed_mps": 10.0, "accel_mps2": null, "steering_deg": 2.5, "yaw_rate_dps": 0.4, "brake": 0.0, "throttle": 0.2, "turn_signal": "left"}
{"t_s": 0.2, "speed_mps": 9.9, "accel_mps2": -0.2, "steering_deg": 3.0, "yaw_rate_dps": 0.3, "brake": 0.1, "throttle": 0.0, "turn_signal": null}
{"t_s": 0.3, "speed_mps": 9.8, "accel_mps2": -0.3, "steering_deg": -1.0, "yaw_rate_dps": -0.2, "brake": 0.3, "throttle": 0.0, "turn_signal": "right"}
"#;

fn err(text: &str) -> TrackError {
    match Track::parse(text.as_bytes()) {
        Ok(t) => panic!("expected an error, parsed {t:?}"),
        Err(e) => e,
    }
}

#[test]
fn csv_and_jsonl_parse_to_the_same_track() {
    let a = Track::parse(CSV.as_bytes()).unwrap();
    let b = Track::parse(JSONL.as_bytes()).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.len(), 4);
    assert_eq!(a.t_s(), &[0.0, 0.1, 0.2, 0.3]);
    assert_eq!(
        a.accel_mps2().unwrap()[1],
        None,
        "an empty cell is a missing sample"
    );
    assert_eq!(a.accel_mps2().unwrap()[2], Some(-0.2));
    let sig = a.turn_signal().unwrap();
    assert_eq!(
        sig,
        &[
            Some(TurnSignal::None),
            Some(TurnSignal::Left),
            None,
            Some(TurnSignal::Right)
        ]
    );
    assert_eq!(a.span(), (0.0, 0.3));
}

#[test]
fn writers_round_trip() {
    let sc = scenario(Manoeuvre::StopThenGo, 7, 0, &SimConfig::realistic());
    let csv = sc.track.to_csv();
    assert_eq!(Track::parse(csv.as_bytes()).unwrap(), sc.track);
    let jsonl = sc.track.to_jsonl();
    let back = Track::parse(jsonl.as_bytes()).unwrap();
    assert_eq!(back.len(), sc.track.len());
    assert_eq!(back.present_columns(), sc.track.present_columns());
    for (x, y) in back.t_s().iter().zip(sc.track.t_s()) {
        assert!((x - y).abs() < 1e-12);
    }
}

#[test]
fn absent_columns_are_none_for_the_track() {
    let t = Track::parse(b"t_s,speed_mps\n0,1\n1,2\n2,\n").unwrap();
    assert_eq!(t.speed_mps().unwrap(), &[Some(1.0), Some(2.0), None]);
    assert!(t.accel_mps2().is_none());
    assert!(t.yaw_rate_dps().is_none());
    assert!(t.turn_signal().is_none());
    assert_eq!(t.present_columns(), vec!["t_s", "speed_mps"]);
    // JSON lines: a column in some lines only is present, missing where a line lacks it.
    let j = Track::parse(b"{\"t_s\":0}\n{\"t_s\":1,\"yaw_rate_dps\":3}\n").unwrap();
    assert_eq!(j.yaw_rate_dps().unwrap(), &[None, Some(3.0)]);
    assert!(j.speed_mps().is_none());
}

#[test]
fn column_order_and_whitespace_do_not_matter() {
    let t = Track::parse(b"\xef\xbb\xbf speed_mps , t_s\r\n5, 0\r\n\r\n6 ,0.5\r\n").unwrap();
    assert_eq!(t.t_s(), &[0.0, 0.5]);
    assert_eq!(t.speed_mps().unwrap(), &[Some(5.0), Some(6.0)]);
}

#[test]
fn non_monotonic_time() {
    let e = err("t_s,speed_mps\n0,1\n0.2,1\n0.1,1\n");
    assert_eq!(e.kind(), "non_monotonic_time");
    assert!(
        matches!(e, TrackError::NonMonotonicTime { line: 4, .. }),
        "{e:?}"
    );
    // Equal timestamps are not increasing either.
    assert_eq!(err("t_s\n0\n0\n").kind(), "non_monotonic_time");
    let j = "{\"t_s\":1}\n{\"t_s\":0.5}\n";
    assert_eq!(err(j).kind(), "non_monotonic_time");
}

#[test]
fn nan_and_infinity_are_refused() {
    let e = err("t_s,speed_mps\n0,1\n0.1,NaN\n");
    assert_eq!(e.kind(), "non_finite");
    assert_eq!(e.column(), Some("speed_mps"));
    assert!(matches!(e, TrackError::NonFinite { line: 3, .. }), "{e:?}");
    assert!(e.to_string().contains("line 3"), "{e}");
    assert_eq!(err("t_s,accel_mps2\n0,inf\n1,0\n").kind(), "non_finite");
    assert_eq!(err("t_s\n0\n1e999\n").kind(), "non_finite");
}

#[test]
fn out_of_range_values() {
    for (col, bad) in [
        ("speed_mps", "-0.5"),
        ("speed_mps", "91"),
        ("accel_mps2", "-16"),
        ("steering_deg", "901"),
        ("yaw_rate_dps", "-181"),
        ("brake", "1.2"),
        ("throttle", "-0.1"),
    ] {
        let e = err(&format!("t_s,{col}\n0,0\n1,{bad}\n"));
        assert_eq!(e.kind(), "out_of_range", "{col}={bad}");
        assert_eq!(e.column(), Some(col));
        assert!(e.to_string().contains(col), "{e}");
    }
    assert_eq!(err("t_s\n-1\n0\n").kind(), "out_of_range");
    assert_eq!(err("t_s\n86000\n86401\n").kind(), "out_of_range");
    // The bounds themselves are valid.
    Track::parse(b"t_s,speed_mps,brake\n0,0,0\n86400,90,1\n").unwrap();
}

#[test]
fn unknown_columns_are_named() {
    let e = err("t_s,speed_kmh\n0,1\n1,2\n");
    assert_eq!(e.kind(), "unknown_column");
    assert_eq!(e.column(), Some("speed_kmh"));
    assert!(e.to_string().contains("speed_kmh"), "{e}");
    let e = err("{\"t_s\":0,\"sped_mps\":1}\n{\"t_s\":1}\n");
    assert_eq!(e.kind(), "unknown_column");
    assert_eq!(e.column(), Some("sped_mps"));
}

#[test]
fn too_few_samples() {
    assert_eq!(err("t_s,speed_mps\n0,1\n").kind(), "empty");
    assert_eq!(err("t_s,speed_mps\n").kind(), "empty");
    assert_eq!(err("").kind(), "empty");
    assert_eq!(err("   \n").kind(), "empty");
    assert_eq!(err("{\"t_s\":0}\n").kind(), "empty");
}

#[test]
fn malformed_input_is_a_parse_error_with_its_line() {
    let e = err("t_s,speed_mps\n0,1\n1,fast\n");
    assert_eq!(e.kind(), "parse");
    assert!(matches!(e, TrackError::Parse { line: 3, .. }), "{e:?}");
    assert_eq!(err("t_s,speed_mps\n0,1\n1\n").kind(), "parse");
    assert_eq!(err("t_s,turn_signal\n0,up\n1,left\n").kind(), "parse");
    assert_eq!(err("t_s,t_s\n0,0\n1,1\n").kind(), "parse");
    assert_eq!(err("t_s\n0\n\n,\n").kind(), "parse");
    assert_eq!(err("{\"t_s\":0}\n{\"t_s\":\"1\"}\n").kind(), "parse");
    assert_eq!(err("{\"t_s\":0}\n{\"speed_mps\":1}\n").kind(), "parse");
    assert_eq!(err("{\"t_s\":0}\n{not json\n").kind(), "parse");
    assert_eq!(err("speed_mps\n1\n2\n").kind(), "missing_column");
    assert_eq!(Track::parse(b"t_s\n0\n\xff\n").unwrap_err().kind(), "parse");
}

#[test]
fn the_sample_limit_bounds_the_work() {
    let mut text = String::from("t_s\n");
    for i in 0..1000 {
        text.push_str(&format!("{i}\n"));
    }
    let limits = TrackLimits { max_samples: 100 };
    let e = Track::parse_with(text.as_bytes(), &limits).unwrap_err();
    assert_eq!(e.kind(), "too_many_samples");
    assert!(matches!(e, TrackError::TooManySamples { limit: 100, .. }));
    assert_eq!(
        Track::parse_with(text.as_bytes(), &TrackLimits { max_samples: 1000 })
            .unwrap()
            .len(),
        1000
    );
    assert_eq!(TrackLimits::default().max_samples, 100_000);
}

#[test]
fn coverage_of_a_clip() {
    let t = Track::parse(b"t_s\n0.05\n5\n9.95\n").unwrap();
    t.covers(0.0, 10.0, 0.1).unwrap();
    t.covers_duration(10.0, 0.1).unwrap();
    t.covers(2.0, 4.0, 0.0).unwrap();
    let e = t.covers(0.0, 12.0, 0.1).unwrap_err();
    assert_eq!(e.kind(), "does_not_cover");
    assert!(e.to_string().contains("12"), "{e}");
    assert_eq!(
        t.covers_duration(10.0, 0.0).unwrap_err().kind(),
        "does_not_cover"
    );
    assert_eq!(
        t.covers(5.0, 4.0, 0.1).unwrap_err().kind(),
        "does_not_cover"
    );
    assert_eq!(
        t.covers(f64::NAN, 4.0, 0.1).unwrap_err().kind(),
        "does_not_cover"
    );
}

#[test]
fn from_columns_applies_the_same_checks() {
    use vlmfuse_annotate::Columns;
    let mut cols = Columns {
        t_s: vec![0.0, 1.0, 2.0],
        speed_mps: Some(vec![Some(1.0), Some(f64::NAN), None]),
        ..Columns::default()
    };
    let e = Track::from_columns(cols.clone()).unwrap_err();
    assert!(matches!(e, TrackError::NonFinite { line: 2, .. }), "{e:?}");
    cols.speed_mps = Some(vec![Some(1.0)]);
    assert_eq!(
        Track::from_columns(cols.clone()).unwrap_err().kind(),
        "parse"
    );
    cols.speed_mps = Some(vec![Some(1.0), Some(2.0), None]);
    let t = Track::from_columns(cols.clone()).unwrap();
    assert_eq!(t.into_columns(), cols);
}

//! The rules on hand-built tracks (exact signals, one property each) and on simulated
//! manoeuvres (noise, realistic dynamics), including the confusable cases.

use vlmfuse_annotate::sim::{scenario, Manoeuvre, SimConfig};
use vlmfuse_annotate::{
    annotate, confidence, AnnotateConfig, Annotation, Columns, Track, TurnSignal, LABELS,
};

/// One sample of a hand-built track; `None` fields are left out of the track.
#[derive(Default, Clone, Copy)]
struct S {
    v: Option<f64>,
    a: Option<f64>,
    steer: Option<f64>,
    yaw: Option<f64>,
    brake: Option<f64>,
    throttle: Option<f64>,
    signal: Option<TurnSignal>,
}

/// A 10 Hz track of `dur_s` from `f(t)`; a column is present when `f(0)` sets it.
fn build(dur_s: f64, f: impl Fn(f64) -> S) -> Track {
    let n = (dur_s * 10.0).round() as usize + 1;
    let t: Vec<f64> = (0..n).map(|i| i as f64 / 10.0).collect();
    let s: Vec<S> = t.iter().map(|&t| f(t)).collect();
    let first = s[0];
    let col = |get: fn(&S) -> Option<f64>, present: bool| {
        present.then(|| s.iter().map(get).collect::<Vec<_>>())
    };
    let cols = Columns {
        speed_mps: col(|x| x.v, first.v.is_some()),
        accel_mps2: col(|x| x.a, first.a.is_some()),
        steering_deg: col(|x| x.steer, first.steer.is_some()),
        yaw_rate_dps: col(|x| x.yaw, first.yaw.is_some()),
        brake: col(|x| x.brake, first.brake.is_some()),
        throttle: col(|x| x.throttle, first.throttle.is_some()),
        turn_signal: first
            .signal
            .is_some()
            .then(|| s.iter().map(|x| x.signal).collect()),
        t_s: t,
    };
    Track::from_columns(cols).unwrap()
}

/// A small deterministic wobble standing in for sensor noise.
fn wob(t: f64, amp: f64) -> f64 {
    amp * (7.3 * t).sin() * (2.9 * t + 1.0).cos()
}

/// Speed and acceleration of a constant-acceleration phase `a` between `t0` and `t1`.
fn speed_profile(t: f64, v0: f64, a: f64, t0: f64, t1: f64) -> (f64, f64) {
    if t < t0 {
        (v0, 0.0)
    } else if t < t1 {
        ((v0 + a * (t - t0)).max(0.0), a)
    } else {
        ((v0 + a * (t1 - t0)).max(0.0), 0.0)
    }
}

fn ann(track: &Track) -> Annotation {
    annotate(track, None, &AnnotateConfig::default())
}

#[test]
fn a_brake_is_a_brake_and_evidence_says_why() {
    let tr = build(8.0, |t| {
        let (v, a) = speed_profile(t, 20.0, -3.0, 2.0, 4.0);
        S {
            v: Some(v),
            a: Some(a + wob(t, 0.1)),
            ..S::default()
        }
    });
    let a = ann(&tr);
    let d = a.get("brake").expect("decided");
    assert!(d.value);
    assert!(d.confidence > 0.9, "{d:?}");
    let e = &d.evidence[0];
    assert_eq!(e.signal, "accel_mps2");
    assert_eq!(e.threshold, -1.5);
    assert!(e.value <= -2.5 && e.margin >= 1.0, "{e:?}");
    assert!((1.9..2.6).contains(&e.t_s), "{e:?}");
    assert_eq!(a.value("accelerate"), Some(false));
    assert_eq!(a.value("stop"), Some(false));
}

#[test]
fn coasting_is_not_a_brake() {
    // Engine drag: 0.6 m/s² for 5 s, no pedal.
    let tr = build(9.0, |t| {
        let (v, a) = speed_profile(t, 20.0, -0.6, 2.0, 7.0);
        S {
            v: Some(v),
            a: Some(a + wob(t, 0.05)),
            brake: Some(0.0),
            throttle: Some(0.0),
            ..S::default()
        }
    });
    let a = ann(&tr);
    assert_eq!(a.value("brake"), Some(false), "{:?}", a.reason("brake"));
    // Without the accelerometer: the same from differentiated speed.
    let tr = build(9.0, |t| S {
        v: Some(speed_profile(t, 20.0, -0.6, 2.0, 7.0).0),
        ..S::default()
    });
    let a = ann(&tr);
    assert_eq!(a.value("brake"), Some(false), "{:?}", a.reason("brake"));
    assert_eq!(
        a.get("brake").unwrap().evidence[0].signal,
        "accel from speed_mps"
    );
}

#[test]
fn a_deceleration_between_coasting_and_braking_is_undecided() {
    let tr = build(9.0, |t| {
        let (v, a) = speed_profile(t, 20.0, -1.1, 2.0, 7.0);
        S {
            v: Some(v),
            a: Some(a),
            ..S::default()
        }
    });
    let a = ann(&tr);
    assert_eq!(a.value("brake"), None);
    assert!(
        a.reason("brake").unwrap().contains("between"),
        "{:?}",
        a.reason("brake")
    );
}

#[test]
fn the_brake_pedal_with_some_deceleration_is_a_brake() {
    // A light brake (0.6 m/s²) that the deceleration alone would leave undecided.
    let tr = build(8.0, |t| {
        let (v, a) = speed_profile(t, 15.0, -0.9, 2.0, 5.0);
        S {
            v: Some(v),
            a: Some(a),
            brake: Some(if (2.0..5.0).contains(&t) { 0.35 } else { 0.0 }),
            ..S::default()
        }
    });
    let d = ann(&tr).get("brake").cloned().expect("decided");
    assert!(d.value);
    assert_eq!(d.evidence[0].signal, "brake");
    // Holding the pedal at a standstill is not braking.
    let tr = build(6.0, |_| S {
        v: Some(0.0),
        a: Some(0.0),
        brake: Some(0.5),
        ..S::default()
    });
    assert_ne!(ann(&tr).value("brake"), Some(true));
}

#[test]
fn acceleration_needs_rising_speed() {
    let tr = build(8.0, |t| {
        let (v, a) = speed_profile(t, 5.0, 2.0, 2.0, 5.0);
        S {
            v: Some(v),
            a: Some(a),
            ..S::default()
        }
    });
    let a = ann(&tr);
    assert_eq!(a.value("accelerate"), Some(true));
    assert_eq!(a.value("brake"), Some(false));
    // The accelerometer reads 2 m/s² (a slope, a mounting error) but the speed is flat.
    let tr = build(8.0, |t| S {
        v: Some(10.0),
        a: Some(if (2.0..5.0).contains(&t) { 2.0 } else { 0.0 }),
        ..S::default()
    });
    let a = ann(&tr);
    assert_eq!(a.value("accelerate"), None);
    assert!(a.reason("accelerate").unwrap().contains("did not rise"));
}

#[test]
fn a_standstill_is_a_stop_and_creeping_is_not() {
    let stop = build(10.0, |t| {
        let (v, a) = speed_profile(t, 8.0, -4.0, 1.0, 3.0);
        S {
            v: Some(v),
            a: Some(a),
            ..S::default()
        }
    });
    let a = ann(&stop);
    assert_eq!(a.value("stop"), Some(true));
    assert_eq!(a.value("brake"), Some(true));
    let creep = build(12.0, |t| S {
        v: Some(0.9 + 0.3 * (t / 2.0).sin()),
        ..S::default()
    });
    let a = ann(&creep);
    assert_eq!(a.value("stop"), Some(false), "{:?}", a.reason("stop"));
    // Rolling through 0.2 m/s for half a second is neither a clear stop nor clearly moving.
    let roll = build(10.0, |t| S {
        v: Some(if (4.0..4.5).contains(&t) { 0.2 } else { 1.5 }),
        ..S::default()
    });
    assert_eq!(ann(&roll).value("stop"), None);
}

#[test]
fn a_stop_needs_the_speed() {
    let tr = build(10.0, |t| S {
        a: Some(speed_profile(t, 8.0, -4.0, 1.0, 3.0).1),
        ..S::default()
    });
    let a = ann(&tr);
    assert_eq!(a.value("stop"), None);
    assert!(a.reason("stop").unwrap().contains("speed_mps"));
    assert_eq!(a.value("brake"), Some(true));
}

/// Heading change by integrating a yaw rate: 18 °/s for 5 s is 90°.
fn turn(sign: f64, by_steering: bool) -> Track {
    build(10.0, move |t| {
        let yaw = if (2.0..7.0).contains(&t) {
            18.0 * sign
        } else {
            0.0
        };
        let v = 8.0;
        // Inverse bicycle model with the default ratio 15 and wheelbase 2.8 m.
        let steer = 15.0 * (yaw.to_radians() * 2.8 / v).atan().to_degrees();
        S {
            v: Some(v),
            yaw: (!by_steering).then_some(yaw + wob(t, 0.3)),
            steer: by_steering.then_some(steer + wob(t, 1.0)),
            ..S::default()
        }
    })
}

#[test]
fn turns_in_both_directions_positive_is_left() {
    for by_steering in [false, true] {
        let a = ann(&turn(1.0, by_steering));
        assert_eq!(a.value("turn_left"), Some(true), "steering: {by_steering}");
        assert_eq!(a.value("turn_right"), Some(false));
        assert_eq!(a.value("merge"), Some(false), "{:?}", a.reason("merge"));
        let e = &a.get("turn_left").unwrap().evidence[0];
        assert!((85.0..95.0).contains(&e.value), "{e:?}");
        let a = ann(&turn(-1.0, by_steering));
        assert_eq!(a.value("turn_right"), Some(true));
        assert_eq!(a.value("turn_left"), Some(false));
    }
    let a = ann(&turn(1.0, true));
    assert!(a.get("turn_left").unwrap().evidence[0]
        .signal
        .contains("bicycle"));
}

/// A lane change to the left at 15 m/s: the yaw rate swings one way and back (a full sine
/// period), so the heading rises a few degrees and returns, and the car ends one lane over.
fn lane_change(signal: Option<TurnSignal>, amp_dps: f64) -> Track {
    build(12.0, move |t| {
        let yaw = if (3.0..7.0).contains(&t) {
            amp_dps * (2.0 * std::f64::consts::PI * (t - 3.0) / 4.0).sin()
        } else {
            0.0
        };
        S {
            v: Some(15.0),
            yaw: Some(yaw),
            signal: signal.map(|s| {
                if (2.0..7.0).contains(&t) {
                    s
                } else {
                    TurnSignal::None
                }
            }),
            ..S::default()
        }
    })
}

#[test]
fn a_lane_change_is_a_merge_not_a_turn() {
    // Peak heading 2·amp/ω = 7.6°; lateral ≈ 15 m/s · ∫heading ≈ 3.6 m.
    let a = ann(&lane_change(Some(TurnSignal::Left), 6.0));
    let d = a.get("merge").expect("decided");
    assert!(d.value, "{d:?}");
    assert!(
        d.evidence[0].value > 3.0,
        "lateral to the left is positive: {d:?}"
    );
    assert!(d.evidence[0].note.contains("with the turn signal"));
    assert_eq!(a.value("turn_left"), Some(false));
    assert_eq!(a.value("turn_right"), Some(false));
    // Without the signal, the same motion still clears the unsignalled threshold.
    let a = ann(&lane_change(None, 6.0));
    assert_eq!(a.value("merge"), Some(true));
    // A smaller drift (about 2.7 m) counts only with the signal on that side…
    assert_eq!(
        ann(&lane_change(Some(TurnSignal::Left), 4.5)).value("merge"),
        Some(true)
    );
    let a = ann(&lane_change(Some(TurnSignal::None), 4.5));
    assert_eq!(a.value("merge"), None, "{:?}", a.get("merge"));
    // …not with the other side's signal.
    assert_eq!(
        ann(&lane_change(Some(TurnSignal::Right), 4.5)).value("merge"),
        None
    );
    // To the right, the lateral displacement is negative.
    let a = ann(&lane_change(Some(TurnSignal::Right), -6.0));
    assert!(a.get("merge").unwrap().evidence[0].value < -3.0);
}

#[test]
fn straight_driving_is_no_merge_and_no_turn() {
    let tr = build(12.0, |t| S {
        v: Some(20.0),
        yaw: Some(wob(t, 0.5)),
        signal: Some(TurnSignal::None),
        ..S::default()
    });
    let a = ann(&tr);
    for l in [
        "merge",
        "turn_left",
        "turn_right",
        "brake",
        "accelerate",
        "stop",
    ] {
        assert_eq!(a.value(l), Some(false), "{l}: {:?}", a.reason(l));
    }
    // A turn signal with no motion to explain it: no confident "no merge".
    let tr = build(12.0, |t| S {
        v: Some(20.0),
        yaw: Some(0.0),
        signal: Some(if t > 5.0 {
            TurnSignal::Left
        } else {
            TurnSignal::None
        }),
        ..S::default()
    });
    assert_eq!(ann(&tr).value("merge"), None);
}

#[test]
fn missing_columns_leave_labels_undecided_not_guessed() {
    // Speed only: longitudinal labels decided, lateral ones unknown.
    let tr = build(10.0, |t| S {
        v: Some(10.0 + wob(t, 0.05)),
        ..S::default()
    });
    let a = ann(&tr);
    for l in ["turn_left", "turn_right", "merge"] {
        assert_eq!(a.value(l), None, "{l}");
        assert!(
            a.reason(l).unwrap().contains("yaw_rate_dps"),
            "{:?}",
            a.reason(l)
        );
    }
    assert_eq!(a.value("brake"), Some(false));
    assert_eq!(a.value("stop"), Some(false));
    let mut unknown = a.unknown();
    unknown.sort();
    assert_eq!(unknown, vec!["merge", "turn_left", "turn_right"]);
    // Yaw rate only: turns decided, but no speed means no stop, no brake, no lateral motion.
    let tr = build(10.0, |_| S {
        yaw: Some(0.0),
        ..S::default()
    });
    let a = ann(&tr);
    assert_eq!(a.value("turn_left"), Some(false));
    for l in ["brake", "accelerate", "stop", "merge"] {
        assert_eq!(a.value(l), None, "{l}");
    }
    // Steering without speed cannot give a yaw rate.
    let tr = build(10.0, |_| S {
        steer: Some(90.0),
        ..S::default()
    });
    assert_eq!(ann(&tr).value("turn_left"), None);
    // A column with most cells empty counts as absent.
    let tr = build(10.0, |t| S {
        v: Some(10.0),
        yaw: if t < 0.05 || (t * 10.0).round() as i64 % 3 == 0 {
            Some(30.0)
        } else {
            None
        },
        ..S::default()
    });
    let a = ann(&tr);
    assert_eq!(a.value("turn_left"), None);
    assert!(
        a.reason("turn_left").unwrap().contains('%'),
        "{:?}",
        a.reason("turn_left")
    );
}

#[test]
fn a_window_restricts_the_samples() {
    let tr = build(20.0, |t| {
        let (v, a) = speed_profile(t, 20.0, -3.0, 2.0, 4.0);
        S {
            v: Some(v),
            a: Some(a),
            ..S::default()
        }
    });
    let cfg = AnnotateConfig::default();
    assert_eq!(annotate(&tr, None, &cfg).value("brake"), Some(true));
    let late = annotate(&tr, Some((10.0, 20.0)), &cfg);
    assert_eq!(late.value("brake"), Some(false));
    assert_eq!((late.start_s, late.end_s, late.samples), (10.0, 20.0, 101));
    let none = annotate(&tr, Some((30.0, 40.0)), &cfg);
    assert!(none.labels.is_empty());
    assert_eq!(none.undecided.len(), LABELS.len());
}

#[test]
fn an_invalid_config_decides_nothing() {
    let cfg = AnnotateConfig {
        brake_decel_mps2: -1.0,
        ..AnnotateConfig::default()
    };
    let a = annotate(&turn(1.0, false), None, &cfg);
    assert!(a.labels.is_empty());
    assert!(a.undecided[0].reason.contains("brake_decel_mps2"));
}

#[test]
fn annotation_serialises_to_json() {
    let a = ann(&turn(1.0, false));
    let json = serde_json::to_string(&a).unwrap();
    assert!(json.contains("\"turn_left\""));
    let back: Annotation = serde_json::from_str(&json).unwrap();
    assert_eq!(back.labels.len(), a.labels.len());
    assert_eq!(back.value("turn_left"), Some(true));
}

#[test]
fn confidence_grows_with_the_margin() {
    assert_eq!(confidence(0.0, 1.5, 0.25), 0.5);
    assert_eq!(confidence(-1.0, 1.5, 0.25), 0.5);
    let c1 = confidence(0.375, 1.5, 0.25);
    assert!((c1 - 1.0 / (1.0 + (-1.0f64).exp())).abs() < 1e-12);
    assert!(confidence(1.5, 1.5, 0.25) > 0.98);
    assert!(confidence(0.5, 1.5, 0.25) < confidence(0.6, 1.5, 0.25));
}

/// Clean simulated clips (every column, default noise, no dropped cells): every label is
/// decided and right, for every manoeuvre, over seeds the thresholds were not tuned on.
#[test]
fn every_manoeuvre_gets_its_labels_right() {
    let sim = SimConfig::default();
    let cfg = AnnotateConfig::default();
    let mut undecided = 0;
    let mut pairs = 0;
    for m in Manoeuvre::ALL {
        for k in 0..8 {
            let sc = scenario(m, 1000 + k, 0, &sim);
            let a = annotate(&sc.track, None, &cfg);
            for l in LABELS {
                pairs += 1;
                let truth = m.truth().contains(&l);
                match a.value(l) {
                    Some(v) => assert_eq!(
                        v,
                        truth,
                        "{} seed {} {l}: {:?}",
                        m.name(),
                        1000 + k,
                        a.get(l)
                    ),
                    None => undecided += 1,
                }
            }
            // Evidence margins are measured in the direction of the decision.
            for d in &a.labels {
                assert!((0.5..=1.0).contains(&d.confidence), "{d:?}");
                for e in &d.evidence {
                    assert!(e.margin >= 0.0, "{d:?}");
                }
            }
            assert_eq!(a.labels.len() + a.undecided.len(), LABELS.len());
        }
    }
    // Clean, complete tracks leave almost nothing undecided.
    assert!(undecided * 50 <= pairs, "{undecided} of {pairs} undecided");
}

#[test]
fn confusable_manoeuvres_on_simulated_tracks() {
    let sim = SimConfig::default();
    let cfg = AnnotateConfig::default();
    for k in 0..10 {
        for m in [
            Manoeuvre::LaneChangeLeft { signal: true },
            Manoeuvre::LaneChangeRight { signal: false },
        ] {
            let a = annotate(&scenario(m, 2000 + k, 0, &sim).track, None, &cfg);
            assert_eq!(
                a.value("merge"),
                Some(true),
                "{} {k}: {:?}",
                m.name(),
                a.reason("merge")
            );
            assert_ne!(a.value("turn_left"), Some(true));
            assert_ne!(a.value("turn_right"), Some(true));
        }
        let a = annotate(
            &scenario(Manoeuvre::Coast, 2000 + k, 0, &sim).track,
            None,
            &cfg,
        );
        assert_ne!(a.value("brake"), Some(true));
        let a = annotate(
            &scenario(Manoeuvre::Creep, 2000 + k, 0, &sim).track,
            None,
            &cfg,
        );
        assert_ne!(a.value("stop"), Some(true));
        for m in [Manoeuvre::TurnLeft, Manoeuvre::TurnRight] {
            let a = annotate(&scenario(m, 2000 + k, 0, &sim).track, None, &cfg);
            assert_ne!(a.value("merge"), Some(true), "{} {k}", m.name());
        }
    }
}

#[test]
fn a_gentle_bend_then_a_straight_is_not_a_merge() {
    // A motorway bend: 10° at 1.7 °/s (under the "straight" yaw level), then 6 s straight at
    // 25 m/s. Measured against the mean heading the straight would drift 13 m sideways.
    let tr = build(12.0, |t| S {
        v: Some(25.0),
        yaw: Some(if (0.0..6.0).contains(&t) {
            10.0 / 6.0
        } else {
            0.0
        }),
        signal: Some(TurnSignal::None),
        ..S::default()
    });
    let a = ann(&tr);
    assert_ne!(a.value("merge"), Some(true), "{:?}", a.get("merge"));
    assert_eq!(a.value("turn_left"), Some(false));
}

#[test]
fn the_largest_track_is_annotated_in_bounded_time() {
    // 100 000 samples (the default limit) of weaving and speed changes, every column: the
    // rules are O(samples), so this takes well under a second even in a debug build.
    let n = 100_000;
    let tr = build((n - 1) as f64 / 10.0, |t| S {
        v: Some(15.0 + 5.0 * (t / 20.0).sin()),
        a: Some(0.25 * (t / 20.0).cos()),
        steer: Some(30.0 * (t / 3.0).sin()),
        // Under the "straight" yaw level everywhere: the most lane-change windows to try.
        yaw: Some(1.5 * (t / 3.0).sin()),
        brake: Some(0.0),
        throttle: Some(0.2),
        signal: Some(TurnSignal::None),
    });
    assert_eq!(tr.len(), n);
    let start = std::time::Instant::now();
    let a = ann(&tr);
    let took = start.elapsed();
    assert_eq!(a.labels.len() + a.undecided.len(), LABELS.len());
    assert!(took.as_secs_f64() < 20.0, "{took:?}");
    println!("annotated {n} samples in {took:?}");
}

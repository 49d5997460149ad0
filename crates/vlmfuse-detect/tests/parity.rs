//! Parity with ultralytics 8.4.190 on the committed tiny YOLO11 (random weights, patched class
//! heads; scripts/parity/yolo_detect.py says how it was made): the predictor's letterboxed
//! input, its decoding + NMS + box scaling, the whole ONNX path, and the trackers' ids.

mod support;

use support::parity::{check_assignments, check_onnx, check_pure, check_tracker, committed};

#[test]
fn letterbox_and_nms_match_ultralytics_on_its_raw_outputs() {
    let r = check_pure(&committed());
    eprintln!("{r:#?}");
    assert_eq!(r.frames, 6);
    // Bit-exact preprocessing (the issue allows one grey level; OpenCV's rounding is mirrored).
    assert_eq!(r.max_grey_diff, 0, "{} pixels differ", r.grey_mismatches);
    assert_eq!(r.max_tensor_diff, 0.0);
    assert!(
        r.kept_set_mismatches.is_empty(),
        "{:#?}",
        r.kept_set_mismatches
    );
    assert_eq!(r.settings, 18);
    // Some settings keep nothing, some are cut by max_det: hundreds of boxes in all.
    assert!(r.boxes > 1000, "{} boxes", r.boxes);
    assert!(r.max_box_diff <= 1e-3, "box diff {}", r.max_box_diff);
    assert!(r.max_score_diff <= 1e-6, "score diff {}", r.max_score_diff);
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh (ONNX Runtime)"]
fn the_onnx_detector_matches_ultralytics_predict() {
    let r = check_onnx(&committed());
    eprintln!("{r:#?}");
    assert_eq!(r.max_tensor_diff, 0.0);
    assert!(r.max_raw_diff <= 1e-4, "raw output diff {}", r.max_raw_diff);
    assert!(
        r.kept_set_mismatches.is_empty(),
        "{:#?}",
        r.kept_set_mismatches
    );
    assert!(r.boxes > 1000);
    assert!(r.max_box_diff <= 1e-3, "box diff {}", r.max_box_diff);
}

#[test]
fn tracker_ids_match_ultralytics_botsort_and_bytetrack() {
    let r = check_tracker(&committed());
    eprintln!("{r:#?}");
    assert!(r.mismatches.is_empty(), "{:#?}", r.mismatches);
    assert_eq!(r.runs, 4);
    assert_eq!(r.frames, 4 * 60);
    assert!(r.tracks_compared > 600, "{}", r.tracks_compared);
    assert!(r.max_box_diff <= 1e-3, "box diff {}", r.max_box_diff);
}

#[test]
fn the_assignment_matches_laps_lapjv_with_a_cost_limit() {
    let (n, bad) = check_assignments(&committed());
    assert_eq!(n, 60);
    assert!(bad.is_empty(), "{bad:#?}");
}

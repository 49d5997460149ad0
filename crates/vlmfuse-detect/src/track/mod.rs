//! Multi-object tracking across a clip's frames: BoT-SORT (without ReID and without camera
//! motion compensation) and ByteTrack, as ultralytics implements them
//! (`ultralytics/trackers/bot_sort.py`, `byte_tracker.py`, `utils/stracks.py`, 8.4.190).
//!
//! Why a tracker at all: a detector on single frames fires on things that are not there for a
//! frame or two. A label says "a traffic light is ahead" only when one object is seen across
//! frames, and a track is what makes "the same object" checkable.
//!
//! Why follow ultralytics line by line (the two-stage association, the unconfirmed tracks,
//! the lost-track buffer, the duplicate removal and their quirks, such as a track removed for
//! staleness staying in the lost pool for one more frame): the paper's annotator ran
//! ultralytics' BoT-SORT, and the parity test checks that the same detections give the same
//! track ids frame by frame. Without ReID and GMC, BoT-SORT is ByteTrack with a Kalman filter
//! on `(cx, cy, w, h)` instead of `(cx, cy, aspect, h)`; both are here.

mod assign;
pub mod kalman;

pub use assign::linear_assignment;

use crate::decode::Detection;
use kalman::{Cov, Layout, Mean};
use serde::{Deserialize, Serialize};

/// Which tracker (ultralytics' `tracker_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum TrackerKind {
    /// BoT-SORT without ReID and GMC (the paper's tracker).
    #[default]
    Botsort,
    Bytetrack,
}

/// ultralytics' tracker settings (`botsort.yaml` / `bytetrack.yaml`); the defaults are theirs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackerConfig {
    pub kind: TrackerKind,
    /// Detections at or above this score take part in the first association.
    pub track_high_thresh: f32,
    /// Detections above this (and below the high threshold) only continue existing tracks.
    pub track_low_thresh: f32,
    /// An unmatched detection starts a track only at or above this score.
    pub new_track_thresh: f32,
    /// Frames a lost track is kept for re-identification.
    pub track_buffer: u32,
    /// Cost limit of the first association (1 - IoU, or 1 - IoU x score with `fuse_score`).
    pub match_thresh: f64,
    /// Weigh the IoU by the detection's score in the first association.
    pub fuse_score: bool,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            kind: TrackerKind::Botsort,
            track_high_thresh: 0.25,
            track_low_thresh: 0.1,
            new_track_thresh: 0.25,
            track_buffer: 30,
            match_thresh: 0.8,
            fuse_score: true,
        }
    }
}

impl TrackerConfig {
    pub fn validate(&self) -> Result<(), String> {
        let unit = |v: f64| (0.0..=1.0).contains(&v);
        if !unit(self.track_high_thresh as f64)
            || !unit(self.track_low_thresh as f64)
            || !unit(self.new_track_thresh as f64)
            || !unit(self.match_thresh)
        {
            return Err("tracker thresholds must be in [0, 1]".into());
        }
        if self.track_low_thresh > self.track_high_thresh {
            return Err(format!(
                "track_low_thresh {} is above track_high_thresh {}",
                self.track_low_thresh, self.track_high_thresh
            ));
        }
        Ok(())
    }

    fn layout(&self) -> Layout {
        match self.kind {
            TrackerKind::Botsort => Layout::Xywh,
            TrackerKind::Bytetrack => Layout::Xyah,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    New,
    Tracked,
    Lost,
    Removed,
}

/// ultralytics' `STrack` / `BOTrack`. A detection becomes one; a new track is that object.
#[derive(Debug, Clone)]
struct STrack {
    track_id: u64,
    is_activated: bool,
    state: State,
    score: f32,
    class: usize,
    /// Index of the detection in its frame's input.
    idx: usize,
    /// The detection's `(left, top, w, h)` (`f32`, as numpy keeps it).
    tlwh0: [f32; 4],
    kf: Option<(Mean, Cov)>,
    start_frame: u64,
    frame_id: u64,
}

impl STrack {
    fn from_detection(d: &Detection, idx: usize) -> Self {
        // Boxes.xywh (f32), then xywh2ltwh on the f64 row ultralytics concatenates.
        let b = d.xyxy;
        let (cx, cy) = ((b[0] + b[2]) / 2.0, (b[1] + b[3]) / 2.0);
        let (w, h) = (b[2] - b[0], b[3] - b[1]);
        let tlwh0 = [
            (cx as f64 - w as f64 / 2.0) as f32,
            (cy as f64 - h as f64 / 2.0) as f32,
            w,
            h,
        ];
        Self {
            track_id: 0,
            is_activated: false,
            state: State::New,
            score: d.score,
            class: d.class,
            idx,
            tlwh0,
            kf: None,
            start_frame: 0,
            frame_id: 0,
        }
    }

    /// `(left, top, w, h)` from the filter's state (or the detection before it has one).
    fn tlwh(&self, layout: Layout) -> [f64; 4] {
        match &self.kf {
            None => self.tlwh0.map(f64::from),
            Some((m, _)) => {
                let (w, h) = match layout {
                    Layout::Xywh => (m[2], m[3]),
                    Layout::Xyah => (m[2] * m[3], m[3]),
                };
                [m[0] - w / 2.0, m[1] - h / 2.0, w, h]
            }
        }
    }

    fn xyxy(&self, layout: Layout) -> [f64; 4] {
        let t = self.tlwh(layout);
        [t[0], t[1], t[0] + t[2], t[1] + t[3]]
    }

    /// The measurement `convert_coords(self.tlwh)` of a detection (in `f32` as numpy computes
    /// it on the detection's `f32` box).
    fn measurement(&self, layout: Layout) -> [f64; 4] {
        let t = self.tlwh0;
        let (cx, cy) = (t[0] + t[2] / 2.0, t[1] + t[3] / 2.0);
        match layout {
            Layout::Xywh => [cx, cy, t[2], t[3]].map(f64::from),
            Layout::Xyah => [cx, cy, t[2] / t[3], t[3]].map(f64::from),
        }
    }
}

/// One tracked object in one frame's output: the filtered box, the id, and the score, class
/// and input index of the detection that updated it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TrackOut {
    pub xyxy: [f32; 4],
    pub track_id: u64,
    pub score: f32,
    pub class: usize,
    /// Index of the detection in this frame's input.
    pub idx: usize,
    /// Whether the track is confirmed (activated). [`Tracker::update`] returns only confirmed
    /// tracks; [`Tracker::update_all`] also the ones a detection started this frame.
    pub confirmed: bool,
}

/// The tracker's state across frames. Feed it every frame in order with [`Tracker::update`].
///
/// Tracks live in an arena and the pools hold indices, as ultralytics' lists hold shared
/// objects: one track can sit in two pools for a frame, and the pools keep ultralytics' order
/// (which decides the cost matrices' row order).
#[derive(Debug, Clone)]
pub struct Tracker {
    cfg: TrackerConfig,
    layout: Layout,
    frame_id: u64,
    next_id: u64,
    arena: Vec<STrack>,
    tracked: Vec<usize>,
    lost: Vec<usize>,
    /// Ids of removed tracks (ultralytics keeps the last 1000, repeats included).
    removed: Vec<u64>,
}

impl Tracker {
    pub fn new(cfg: TrackerConfig) -> Self {
        Self {
            layout: cfg.layout(),
            cfg,
            frame_id: 0,
            next_id: 1,
            arena: Vec::new(),
            tracked: Vec::new(),
            lost: Vec::new(),
            removed: Vec::new(),
        }
    }

    /// One frame's detections in, the activated tracks this frame out (ultralytics'
    /// `BYTETracker.update`, step by step, and its output).
    pub fn update(&mut self, dets: &[Detection]) -> Vec<TrackOut> {
        let mut out = self.update_all(dets);
        out.retain(|t| t.confirmed);
        out
    }

    /// As [`Tracker::update`], plus the tracks a detection started this frame (unconfirmed
    /// until their next frame; ultralytics does not output them). A caller counting in how many
    /// frames an object was seen needs that first frame too.
    pub fn update_all(&mut self, dets: &[Detection]) -> Vec<TrackOut> {
        let layout = self.layout;
        self.frame_id += 1;
        let fid = self.frame_id;
        let mut activated: Vec<usize> = Vec::new();
        let mut refind: Vec<usize> = Vec::new();
        let mut lost_now: Vec<usize> = Vec::new();
        let mut removed_now: Vec<u64> = Vec::new();

        let mut high = Vec::new();
        let mut low = Vec::new();
        for (i, d) in dets.iter().enumerate() {
            let (w, h) = (d.xyxy[2] - d.xyxy[0], d.xyxy[3] - d.xyxy[1]);
            if !(w > 0.0 && h > 0.0) {
                continue;
            }
            if d.score >= self.cfg.track_high_thresh {
                high.push(STrack::from_detection(d, i));
            } else if d.score > self.cfg.track_low_thresh {
                low.push(STrack::from_detection(d, i));
            }
        }

        let unconfirmed: Vec<usize> = self
            .tracked
            .iter()
            .copied()
            .filter(|&t| !self.arena[t].is_activated)
            .collect();
        let confirmed: Vec<usize> = self
            .tracked
            .iter()
            .copied()
            .filter(|&t| self.arena[t].is_activated)
            .collect();
        let pool = self.joint(&confirmed, &self.lost);
        for &t in &pool {
            let tr = &mut self.arena[t];
            if let Some((m, p)) = &tr.kf {
                let mut m = *m;
                if tr.state != State::Tracked {
                    if layout == Layout::Xywh {
                        m[6] = 0.0;
                    }
                    m[7] = 0.0;
                }
                tr.kf = Some(layout.predict(&m, p));
            }
        }

        // First association: confident detections against tracked and lost tracks.
        let (matches, u_track, u_det) =
            self.associate(&pool, &high, self.cfg.fuse_score, self.cfg.match_thresh);
        for (it, id) in matches {
            let t = pool[it];
            let was_tracked = self.arena[t].state == State::Tracked;
            self.apply(t, &high[id], fid);
            if was_tracked {
                activated.push(t)
            } else {
                refind.push(t)
            }
        }

        // Second association: the tracked leftovers against the weak detections.
        let r_tracked: Vec<usize> = u_track
            .iter()
            .map(|&i| pool[i])
            .filter(|&t| self.arena[t].state == State::Tracked)
            .collect();
        let u_track2: Vec<usize> = if !r_tracked.is_empty() && !low.is_empty() {
            let (m2, u2, _) = self.associate(&r_tracked, &low, false, 0.5);
            for (it, id) in m2 {
                let t = r_tracked[it];
                let was_tracked = self.arena[t].state == State::Tracked;
                self.apply(t, &low[id], fid);
                if was_tracked {
                    activated.push(t)
                } else {
                    refind.push(t)
                }
            }
            u2
        } else {
            (0..r_tracked.len()).collect()
        };
        for i in u_track2 {
            self.arena[r_tracked[i]].state = State::Lost;
            lost_now.push(r_tracked[i]);
        }

        // Unconfirmed tracks (started last frame) against the confident detections left.
        let rest: Vec<STrack> = u_det.iter().map(|&i| high[i].clone()).collect();
        let u_rest: Vec<usize> = if unconfirmed.is_empty() {
            (0..rest.len()).collect()
        } else {
            let (m3, u_unconf, u_rest) =
                self.associate(&unconfirmed, &rest, self.cfg.fuse_score, 0.7);
            for (it, id) in m3 {
                self.apply(unconfirmed[it], &rest[id], fid);
                activated.push(unconfirmed[it]);
            }
            for i in u_unconf {
                let t = &mut self.arena[unconfirmed[i]];
                t.state = State::Removed;
                removed_now.push(t.track_id);
            }
            u_rest
        };
        for i in u_rest {
            let mut t = rest[i].clone();
            if t.score < self.cfg.new_track_thresh {
                continue;
            }
            t.track_id = self.next_id;
            self.next_id += 1;
            t.kf = Some(layout.initiate(t.measurement(layout)));
            t.state = State::Tracked;
            t.is_activated = fid == 1;
            t.frame_id = fid;
            t.start_frame = fid;
            self.arena.push(t);
            activated.push(self.arena.len() - 1);
        }

        // Stale lost tracks are marked removed. ultralytics filters the lost pool by the
        // removed list before extending that list, so they stay in the pool one more frame.
        for &t in &self.lost {
            let tr = &mut self.arena[t];
            if fid - tr.frame_id > self.cfg.track_buffer as u64 {
                tr.state = State::Removed;
                removed_now.push(tr.track_id);
            }
        }

        // merge_track_pools.
        let still: Vec<usize> = self
            .tracked
            .iter()
            .copied()
            .filter(|&t| self.arena[t].state == State::Tracked)
            .collect();
        let tracked = self.joint(&still, &activated);
        let tracked = self.joint(&tracked, &refind);
        let mut lost = self.sub(&self.lost, &tracked);
        lost.extend(lost_now);
        let lost: Vec<usize> = lost
            .into_iter()
            .filter(|&t| !self.removed.contains(&self.arena[t].track_id))
            .collect();
        let (tracked, lost) = self.remove_duplicates(tracked, lost);
        self.removed.extend(removed_now);
        if self.removed.len() > 1000 {
            let cut = self.removed.len() - 1000;
            self.removed.drain(..cut);
        }
        self.tracked = tracked;
        self.lost = lost;
        self.tracked
            .iter()
            .map(|&t| &self.arena[t])
            .filter(|t| t.is_activated || t.frame_id == fid)
            .map(|t| TrackOut {
                xyxy: t.xyxy(layout).map(|v| v as f32),
                track_id: t.track_id,
                score: t.score,
                class: t.class,
                idx: t.idx,
                confirmed: t.is_activated,
            })
            .collect()
    }

    /// `a` then the tracks of `b` whose id is not in `a`.
    fn joint(&self, a: &[usize], b: &[usize]) -> Vec<usize> {
        let mut out = a.to_vec();
        for &t in b {
            let id = self.arena[t].track_id;
            if !a.iter().any(|&x| self.arena[x].track_id == id) {
                out.push(t);
            }
        }
        out
    }

    /// The tracks of `a` whose id is not in `b`.
    fn sub(&self, a: &[usize], b: &[usize]) -> Vec<usize> {
        a.iter()
            .copied()
            .filter(|&t| {
                !b.iter()
                    .any(|&x| self.arena[x].track_id == self.arena[t].track_id)
            })
            .collect()
    }

    /// Cost matrix (1 - IoU, optionally fused with the detection score) and assignment.
    fn associate(
        &self,
        tracks: &[usize],
        dets: &[STrack],
        fuse: bool,
        limit: f64,
    ) -> assign::Assignment {
        let boxes: Vec<[f32; 4]> = tracks
            .iter()
            .map(|&t| self.arena[t].xyxy(self.layout).map(|v| v as f32))
            .collect();
        let dboxes: Vec<[f32; 4]> = dets
            .iter()
            .map(|d| d.xyxy(self.layout).map(|v| v as f32))
            .collect();
        let mut cost: Vec<f32> = iou_matrix(&boxes, &dboxes)
            .into_iter()
            .map(|v| 1.0 - v)
            .collect();
        if fuse {
            fuse_score(&mut cost, dets);
        }
        linear_assignment(&cost, tracks.len(), dets.len(), limit)
    }

    /// `update` (a tracked track) or `re_activate` (a lost one) with a matched detection.
    fn apply(&mut self, t: usize, det: &STrack, fid: u64) {
        let layout = self.layout;
        let t = &mut self.arena[t];
        if let Some((m, p)) = &t.kf {
            t.kf = Some(layout.update(m, p, det.measurement(layout)));
        }
        t.state = State::Tracked;
        t.is_activated = true;
        t.frame_id = fid;
        t.score = det.score;
        t.class = det.class;
        t.idx = det.idx;
    }

    /// Tracked and lost tracks that overlap (1 - IoU < 0.15): the younger of each pair goes.
    fn remove_duplicates(&self, a: Vec<usize>, b: Vec<usize>) -> (Vec<usize>, Vec<usize>) {
        let bx = |v: &[usize]| -> Vec<[f32; 4]> {
            v.iter()
                .map(|&t| self.arena[t].xyxy(self.layout).map(|x| x as f32))
                .collect()
        };
        let iou = iou_matrix(&bx(&a), &bx(&b));
        let mut drop_a = vec![false; a.len()];
        let mut drop_b = vec![false; b.len()];
        for p in 0..a.len() {
            for q in 0..b.len() {
                if 1.0 - iou[p * b.len() + q] < 0.15 {
                    let (tp, tq) = (&self.arena[a[p]], &self.arena[b[q]]);
                    if tp.frame_id - tp.start_frame > tq.frame_id - tq.start_frame {
                        drop_b[q] = true;
                    } else {
                        drop_a[p] = true;
                    }
                }
            }
        }
        let keep = |v: Vec<usize>, drop: &[bool]| -> Vec<usize> {
            v.into_iter()
                .zip(drop)
                .filter(|(_, &d)| !d)
                .map(|(t, _)| t)
                .collect()
        };
        (keep(a, &drop_a), keep(b, &drop_b))
    }
}

fn iou_matrix(a: &[[f32; 4]], b: &[[f32; 4]]) -> Vec<f32> {
    let mut out = Vec::with_capacity(a.len() * b.len());
    for p in a {
        let pa = (p[2] - p[0]) * (p[3] - p[1]);
        for q in b {
            let iw = (p[2].min(q[2]) - p[0].max(q[0])).max(0.0);
            let ih = (p[3].min(q[3]) - p[1].max(q[1])).max(0.0);
            let inter = iw * ih;
            let qa = (q[2] - q[0]) * (q[3] - q[1]);
            out.push(inter / (qa + pa - inter + 1e-7));
        }
    }
    out
}

/// `1 - (1 - cost) x score` per detection column.
fn fuse_score(cost: &mut [f32], dets: &[STrack]) {
    if dets.is_empty() {
        return;
    }
    for row in cost.chunks_mut(dets.len()) {
        for (c, d) in row.iter_mut().zip(dets) {
            *c = 1.0 - (1.0 - *c) * d.score;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn det(x: f32, y: f32, score: f32) -> Detection {
        Detection {
            xyxy: [x, y, x + 40.0, y + 80.0],
            score,
            class: 0,
        }
    }

    #[test]
    fn a_moving_object_keeps_its_id_and_a_one_frame_blip_gets_none_out() {
        let mut t = Tracker::new(TrackerConfig::default());
        let out = t.update(&[det(100.0, 100.0, 0.9)]);
        assert_eq!(out.len(), 1);
        let id = out[0].track_id;
        for k in 1..10 {
            let mut dets = vec![det(100.0 + 6.0 * k as f32, 100.0, 0.9)];
            if k == 5 {
                dets.push(det(600.0, 300.0, 0.9)); // seen once: never confirmed, never output
            }
            let out = t.update(&dets);
            assert_eq!(out.len(), 1, "frame {k}: {out:?}");
            assert_eq!(out[0].track_id, id);
        }
    }
}

//! A seeded vehicle simulator for scripted manoeuvres, and [`evaluate`], which scores the
//! rules ([`crate::annotate`]) against the manoeuvres' ground truth.
//!
//! Why a simulator: the rules' thresholds need labelled recordings with the hard cases in
//! them — coasting next to braking, creeping next to stopping, lane changes next to turns —
//! and a labelled fleet recording is not something a test can ship. The simulator makes the
//! truth exact by construction: each [`Manoeuvre`] is a script whose intensities are drawn
//! from ranges chosen so the label is unambiguous (a brake decelerates 2–5 m/s², coasting
//! 0.2–0.7), and the noise, missing columns and dropped samples are what a real track has.
//!
//! Model: a kinematic bicycle (wheelbase 2.6–3.0 m, steering ratio 14–17, both drawn per
//! clip, so the rules' fixed 2.8 m / 15 are only approximately right, as on a real fleet)
//! stepped at 100 Hz, with the limits of a passenger car: acceleration ≤ 3 m/s²,
//! deceleration ≤ 8 m/s², jerk ≤ 10 m/s³, steering-wheel rate ≤ 360 °/s, wheel angle
//! ≤ 540°, lateral acceleration ≤ 4 m/s². A driver model holds speed, heading and lane
//! position with proportional controllers. Sensors sample at 10 Hz with 2 ms jitter and
//! Gaussian noise (Box–Muller on a ChaCha8 stream): speed 0.05 m/s (reading exactly 0 at a
//! standstill, like a wheel-speed sensor), acceleration 0.15 m/s², steering 1°, yaw rate
//! 0.5 °/s, pedals 0.01.
//!
//! Everything is deterministic in `(seed, manoeuvre, index)`.

use crate::config::AnnotateConfig;
use crate::rules::{annotate, LABELS};
use crate::track::{Columns, Track, TurnSignal};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use std::fmt;

/// A scripted manoeuvre. Each clip also has some straight cruising around the manoeuvre.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Manoeuvre {
    /// Steady speed 8–25 m/s with mild speed wobble (|a| ≤ 0.15 m/s²). Truth: nothing.
    Cruise,
    /// Brake at 2–5 m/s² for 1.5–3 s, staying above 4 m/s. Truth: brake.
    Brake,
    /// Lift off: engine-drag deceleration 0.2–0.7 m/s² for 3–6 s, no pedal. Truth: nothing.
    Coast,
    /// Accelerate at 1.5–3 m/s² for 2–5 s. Truth: accelerate.
    Accelerate,
    /// Brake at 2–5 m/s² to a standstill, hold it 2–5 s. Truth: brake, stop.
    Stop,
    /// [`Manoeuvre::Stop`], then pull away at 1.5–2.5 m/s². Truth: brake, stop, accelerate.
    StopThenGo,
    /// Creep in a queue at 0.5–1.5 m/s, never stopping. Truth: nothing.
    Creep,
    /// 70–110° left at 5–9 m/s. Truth: turn_left.
    TurnLeft,
    /// 70–110° right at 5–9 m/s. Truth: turn_right.
    TurnRight,
    /// One lane (3.2–3.8 m) left in 3–6 s at 10–25 m/s, with or without the turn signal.
    /// Truth: merge.
    LaneChangeLeft { signal: bool },
    /// One lane right; see [`Manoeuvre::LaneChangeLeft`]. Truth: merge.
    LaneChangeRight { signal: bool },
    /// Brake at 2–4 m/s² from 12–16 m/s to 5–7 m/s, then turn right. Truth: brake, turn_right.
    BrakeThenTurnRight,
}

impl Manoeuvre {
    /// Every manoeuvre, in report order.
    pub const ALL: [Manoeuvre; 14] = [
        Manoeuvre::Cruise,
        Manoeuvre::Brake,
        Manoeuvre::Coast,
        Manoeuvre::Accelerate,
        Manoeuvre::Stop,
        Manoeuvre::StopThenGo,
        Manoeuvre::Creep,
        Manoeuvre::TurnLeft,
        Manoeuvre::TurnRight,
        Manoeuvre::LaneChangeLeft { signal: true },
        Manoeuvre::LaneChangeLeft { signal: false },
        Manoeuvre::LaneChangeRight { signal: true },
        Manoeuvre::LaneChangeRight { signal: false },
        Manoeuvre::BrakeThenTurnRight,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Manoeuvre::Cruise => "cruise",
            Manoeuvre::Brake => "brake",
            Manoeuvre::Coast => "coast",
            Manoeuvre::Accelerate => "accelerate",
            Manoeuvre::Stop => "stop",
            Manoeuvre::StopThenGo => "stop_then_go",
            Manoeuvre::Creep => "creep",
            Manoeuvre::TurnLeft => "turn_left",
            Manoeuvre::TurnRight => "turn_right",
            Manoeuvre::LaneChangeLeft { signal: true } => "lane_change_left_signalled",
            Manoeuvre::LaneChangeLeft { signal: false } => "lane_change_left_unsignalled",
            Manoeuvre::LaneChangeRight { signal: true } => "lane_change_right_signalled",
            Manoeuvre::LaneChangeRight { signal: false } => "lane_change_right_unsignalled",
            Manoeuvre::BrakeThenTurnRight => "brake_then_turn_right",
        }
    }

    /// The labels of [`LABELS`] that are true for this manoeuvre; all others are false.
    pub fn truth(self) -> &'static [&'static str] {
        match self {
            Manoeuvre::Cruise | Manoeuvre::Coast | Manoeuvre::Creep => &[],
            Manoeuvre::Brake => &["brake"],
            Manoeuvre::Accelerate => &["accelerate"],
            Manoeuvre::Stop => &["brake", "stop"],
            Manoeuvre::StopThenGo => &["brake", "stop", "accelerate"],
            Manoeuvre::TurnLeft => &["turn_left"],
            Manoeuvre::TurnRight => &["turn_right"],
            Manoeuvre::LaneChangeLeft { .. } | Manoeuvre::LaneChangeRight { .. } => &["merge"],
            Manoeuvre::BrakeThenTurnRight => &["brake", "turn_right"],
        }
    }

    fn index(self) -> u64 {
        Manoeuvre::ALL.iter().position(|m| *m == self).unwrap_or(0) as u64
    }
}

/// Sensor and recording settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    /// Sensor sampling rate (Hz).
    pub rate_hz: f64,
    /// Timestamp jitter (s, uniform ±).
    pub jitter_s: f64,
    pub speed_sd_mps: f64,
    pub accel_sd_mps2: f64,
    pub steering_sd_deg: f64,
    pub yaw_sd_dps: f64,
    pub pedal_sd: f64,
    /// Share of cells left empty (a dropped CAN frame), per cell.
    pub missing_share: f64,
    /// Drop whole columns at random per clip, as tracks from different vehicles lack
    /// different signals (accel 30 %, yaw rate 30 %, steering 30 % where the yaw rate stays,
    /// pedals 30 %, turn signal 20 %, speed 10 % where the accel stays). Off: every column.
    pub drop_columns: bool,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            rate_hz: 10.0,
            jitter_s: 0.002,
            speed_sd_mps: 0.05,
            accel_sd_mps2: 0.15,
            steering_sd_deg: 1.0,
            yaw_sd_dps: 0.5,
            pedal_sd: 0.01,
            missing_share: 0.0,
            drop_columns: false,
        }
    }
}

impl SimConfig {
    /// The setting [`evaluate`] uses: default noise, 2 % dropped cells, random columns.
    pub fn realistic() -> SimConfig {
        SimConfig {
            missing_share: 0.02,
            drop_columns: true,
            ..SimConfig::default()
        }
    }
}

/// A simulated clip and its truth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Scenario {
    pub manoeuvre: Manoeuvre,
    pub seed: u64,
    pub index: u64,
    pub track: Track,
    /// The true labels ([`Manoeuvre::truth`]); every other label of [`LABELS`] is false.
    pub truth: Vec<String>,
}

/// CSV of a track (see [`Track::to_csv`]), for example files.
pub fn to_csv(track: &Track) -> String {
    track.to_csv()
}

/// JSON lines of a track (see [`Track::to_jsonl`]).
pub fn to_jsonl(track: &Track) -> String {
    track.to_jsonl()
}

const STEP_S: f64 = 0.01;
const MAX_ACCEL: f64 = 3.0;
const MAX_DECEL: f64 = 8.0;
const MAX_JERK: f64 = 10.0;
const WHEEL_RATE_DPS: f64 = 360.0;
const WHEEL_MAX_DEG: f64 = 540.0;
const LAT_ACCEL_MAX: f64 = 4.0;

/// Longitudinal driver intent for one phase.
#[derive(Debug, Clone, Copy)]
enum Long {
    /// Hold a speed (`None`: the speed at the phase start) with a wobble of amplitude `wobble`.
    Cruise {
        v: Option<f64>,
        wobble: f64,
        period: f64,
    },
    /// Constant deceleration command (m/s², positive) with this brake-pedal position.
    Brake { decel: f64, pedal: f64 },
    /// Engine drag: deceleration without pedals.
    Coast { decel: f64 },
    /// Constant acceleration command.
    Accel { a: f64 },
    /// Standing with the brake held.
    Hold { pedal: f64 },
    /// Creep: speed follows `mid + amp·sin(2πt/period)`.
    Creep { mid: f64, amp: f64, period: f64 },
}

/// Lateral driver intent for one phase.
#[derive(Debug, Clone, Copy)]
enum Lat {
    /// Keep the lane.
    Keep,
    /// Change the road heading by this much (rad, + left) at a design lateral acceleration.
    Turn { by: f64, a_lat: f64 },
    /// Move the lane offset by this much (m, + left) over `dur` s (cosine profile).
    Lane { by: f64, dur: f64 },
}

#[derive(Debug, Clone, Copy)]
struct Phase {
    dur: f64,
    long: Long,
    lat: Lat,
    signal: TurnSignal,
}

fn phase(dur: f64, long: Long, lat: Lat) -> Phase {
    Phase {
        dur,
        long,
        lat,
        signal: TurnSignal::None,
    }
}

/// True state at one sim step.
#[derive(Debug, Clone, Copy, Default)]
struct State {
    v: f64,
    a: f64,
    wheel_deg: f64,
    yaw_dps: f64,
    brake: f64,
    throttle: f64,
    signal: Option<TurnSignal>,
}

struct Vehicle {
    x: f64,
    y: f64,
    psi: f64,
    v: f64,
    a: f64,
    wheel_deg: f64,
    ratio: f64,
    wheelbase: f64,
}

impl Vehicle {
    /// One step with an acceleration command and a steering-wheel target.
    fn step(&mut self, a_cmd: f64, wheel_target: f64) -> (f64, f64) {
        let a_cmd = a_cmd.clamp(-MAX_DECEL, MAX_ACCEL);
        let da = (a_cmd - self.a).clamp(-MAX_JERK * STEP_S, MAX_JERK * STEP_S);
        self.a += da;
        if self.v <= 0.0 && self.a < 0.0 {
            self.a = 0.0;
        }
        let v0 = self.v;
        self.v = (self.v + self.a * STEP_S).max(0.0);
        let a_eff = (self.v - v0) / STEP_S;
        if self.v == 0.0 {
            self.a = self.a.max(0.0);
        }
        // Road-wheel limit from the lateral acceleration limit: v² tan(δ)/L ≤ a_lat.
        let mut lim = WHEEL_MAX_DEG;
        if self.v > 0.5 {
            let d = (LAT_ACCEL_MAX * self.wheelbase / (self.v * self.v)).atan();
            lim = lim.min(d.to_degrees() * self.ratio);
        }
        let target = wheel_target.clamp(-lim, lim);
        let dw = (target - self.wheel_deg).clamp(-WHEEL_RATE_DPS * STEP_S, WHEEL_RATE_DPS * STEP_S);
        self.wheel_deg += dw;
        let yaw = self.v * (self.wheel_deg / self.ratio).to_radians().tan() / self.wheelbase;
        self.psi += yaw * STEP_S;
        self.x += self.v * self.psi.cos() * STEP_S;
        self.y += self.v * self.psi.sin() * STEP_S;
        (a_eff, yaw.to_degrees())
    }

    /// Steering-wheel angle for a desired yaw rate (rad/s).
    fn wheel_for(&self, yaw: f64) -> f64 {
        if self.v < 0.5 {
            return 0.0;
        }
        (yaw * self.wheelbase / self.v).atan().to_degrees() * self.ratio
    }
}

/// Runs a script; returns the true state every step.
fn run(mut veh: Vehicle, phases: &[Phase], rng: &mut ChaCha8Rng) -> Vec<State> {
    let mut out = Vec::new();
    let mut road = veh.psi; // road heading
    let (mut ox, mut oy) = (veh.x, veh.y); // lane frame origin
    let mut lane = 0.0; // lane offset target at phase start
    let mut t_total = 0.0;
    let wob_phase: f64 = rng.random_range(0.0..2.0 * PI);
    for p in phases {
        let steps = (p.dur / STEP_S).round() as usize;
        let v_start = veh.v;
        let turn_target = match p.lat {
            Lat::Turn { by, .. } => road + by,
            _ => road,
        };
        for k in 0..steps {
            let tau = k as f64 * STEP_S;
            // Longitudinal.
            let (a_cmd, brake, coasting) = match p.long {
                Long::Cruise { v, wobble, period } => {
                    let vt = v.unwrap_or(v_start);
                    let w = wobble * (2.0 * PI * t_total / period + wob_phase).sin();
                    ((0.8 * (vt - veh.v)).clamp(-0.3, 0.3) + w, 0.0, false)
                }
                Long::Brake { decel, pedal } => (-decel, pedal, false),
                Long::Coast { decel } => (-decel, 0.0, true),
                Long::Accel { a } => (a, 0.0, false),
                Long::Hold { pedal } => (-1.0, pedal, false),
                Long::Creep { mid, amp, period } => {
                    let w = 2.0 * PI / period;
                    let vt = mid + amp * (w * tau).sin();
                    let ff = amp * w * (w * tau).cos();
                    (ff + 1.5 * (vt - veh.v), 0.0, false)
                }
            };
            // Lateral.
            let yaw_des = match p.lat {
                Lat::Keep | Lat::Lane { .. } => {
                    let (yr, ydot) = match p.lat {
                        Lat::Lane { by, dur } => {
                            let s = (tau / dur).min(1.0);
                            let yr = lane + by * (1.0 - (PI * s).cos()) / 2.0;
                            let ydot = if tau < dur {
                                by * PI / (2.0 * dur) * (PI * s).sin()
                            } else {
                                0.0
                            };
                            (yr, ydot)
                        }
                        _ => (lane, 0.0),
                    };
                    let e = -(veh.x - ox) * road.sin() + (veh.y - oy) * road.cos();
                    let v = veh.v.max(0.5);
                    let psi_d = road + ((ydot + 1.0 * (yr - e)) / v).atan();
                    3.0 * wrap(psi_d - veh.psi)
                }
                Lat::Turn { a_lat, .. } => {
                    let v = veh.v.max(0.5);
                    let rmax = (a_lat / v).min(0.6);
                    (2.5 * wrap(turn_target - veh.psi)).clamp(-rmax, rmax)
                }
            };
            let wheel_target = veh.wheel_for(yaw_des);
            let (a, yaw) = veh.step(a_cmd, wheel_target);
            let throttle = if coasting || brake > 0.0 || veh.v == 0.0 {
                0.0
            } else if matches!(p.long, Long::Creep { .. }) {
                0.05
            } else {
                (0.1 + 0.008 * veh.v + 0.25 * a.max(0.0)).min(1.0)
            };
            out.push(State {
                v: veh.v,
                a,
                wheel_deg: veh.wheel_deg,
                yaw_dps: yaw,
                brake,
                throttle,
                signal: Some(p.signal),
            });
            t_total += STEP_S;
        }
        match p.lat {
            Lat::Turn { .. } => {
                road = turn_target;
                ox = veh.x;
                oy = veh.y;
                lane = 0.0;
            }
            Lat::Lane { by, .. } => lane += by,
            Lat::Keep => {}
        }
    }
    out
}

fn wrap(a: f64) -> f64 {
    let mut a = a % (2.0 * PI);
    if a > PI {
        a -= 2.0 * PI;
    }
    if a < -PI {
        a += 2.0 * PI;
    }
    a
}

fn normal(rng: &mut ChaCha8Rng) -> f64 {
    // Box–Muller; 1 − u keeps the log's argument in (0, 1].
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (2.0 * PI * u2).cos()
}

fn u(rng: &mut ChaCha8Rng, a: f64, b: f64) -> f64 {
    rng.random_range(a..b)
}

/// Cruising for a duration drawn from `[lo, hi)` s.
fn cruise(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> Phase {
    let dur = u(rng, lo, hi);
    phase(
        dur,
        Long::Cruise {
            v: None,
            wobble: u(rng, 0.0, 0.15),
            period: u(rng, 3.0, 8.0),
        },
        Lat::Keep,
    )
}

/// The script (initial speed, phases) of one manoeuvre.
fn script(m: Manoeuvre, rng: &mut ChaCha8Rng) -> (f64, Vec<Phase>) {
    let signal_for = |left: bool| {
        if left {
            TurnSignal::Left
        } else {
            TurnSignal::Right
        }
    };
    match m {
        Manoeuvre::Cruise => (u(rng, 8.0, 25.0), vec![cruise(rng, 8.0, 14.0)]),
        Manoeuvre::Brake => {
            let v0 = u(rng, 12.0, 25.0);
            let decel = u(rng, 2.0, 5.0);
            let dur = u(rng, 1.5, 3.0).min((v0 - 4.0) / decel);
            let pedal = 0.08 + decel / 9.0;
            let pre = cruise(rng, 2.0, 4.0);
            let post = cruise(rng, 2.0, 3.0);
            (
                v0,
                vec![
                    pre,
                    phase(dur, Long::Brake { decel, pedal }, Lat::Keep),
                    post,
                ],
            )
        }
        Manoeuvre::Coast => {
            let pre = cruise(rng, 2.0, 4.0);
            let coast = phase(
                u(rng, 3.0, 6.0),
                Long::Coast {
                    decel: u(rng, 0.2, 0.7),
                },
                Lat::Keep,
            );
            let post = cruise(rng, 1.0, 3.0);
            (u(rng, 12.0, 25.0), vec![pre, coast, post])
        }
        Manoeuvre::Accelerate => {
            let v0 = u(rng, 3.0, 15.0);
            let a = u(rng, 1.5, 3.0);
            let dur = u(rng, 2.0, 5.0).min((30.0 - v0) / a);
            let pre = cruise(rng, 2.0, 4.0);
            let post = cruise(rng, 2.0, 3.0);
            (
                v0,
                vec![pre, phase(dur, Long::Accel { a }, Lat::Keep), post],
            )
        }
        Manoeuvre::Stop | Manoeuvre::StopThenGo => {
            let v0 = u(rng, 6.0, 15.0);
            let decel = u(rng, 2.0, 5.0);
            let pedal = 0.08 + decel / 9.0;
            let pre = cruise(rng, 2.0, 3.0);
            let hold = u(rng, 0.3, 0.5);
            let mut ph = vec![
                pre,
                phase(v0 / decel + 0.5, Long::Brake { decel, pedal }, Lat::Keep),
                phase(u(rng, 2.0, 5.0), Long::Hold { pedal: hold }, Lat::Keep),
            ];
            if m == Manoeuvre::StopThenGo {
                ph.push(phase(
                    u(rng, 2.0, 4.0),
                    Long::Accel {
                        a: u(rng, 1.5, 2.5),
                    },
                    Lat::Keep,
                ));
            }
            (v0, ph)
        }
        Manoeuvre::Creep => {
            let mid = u(rng, 0.8, 1.2);
            let amp = u(rng, 0.1, 0.25);
            let creep = phase(
                u(rng, 10.0, 15.0),
                Long::Creep {
                    mid,
                    amp,
                    period: u(rng, 6.0, 10.0),
                },
                Lat::Keep,
            );
            (mid, vec![creep])
        }
        Manoeuvre::TurnLeft | Manoeuvre::TurnRight | Manoeuvre::BrakeThenTurnRight => {
            let left = m == Manoeuvre::TurnLeft;
            let mut ph = Vec::new();
            let v_turn = u(rng, 5.0, 9.0);
            let v0 = if m == Manoeuvre::BrakeThenTurnRight {
                let v0 = u(rng, 12.0, 16.0);
                let v1 = u(rng, 5.0, 7.0);
                let decel = u(rng, 2.0, 4.0);
                ph.push(cruise(rng, 1.5, 3.0));
                ph.push(phase(
                    (v0 - v1) / decel,
                    Long::Brake {
                        decel,
                        pedal: 0.08 + decel / 9.0,
                    },
                    Lat::Keep,
                ));
                v0
            } else {
                ph.push(cruise(rng, 1.0, 2.0));
                v_turn
            };
            let mut lead = cruise(rng, 1.0, 2.0);
            let signalled = rng.random_bool(0.7);
            if signalled {
                lead.signal = signal_for(left);
            }
            ph.push(lead);
            let by = u(rng, 70.0, 110.0).to_radians() * if left { 1.0 } else { -1.0 };
            let a_lat = u(rng, 2.5, 3.5);
            // Long enough for the heading to settle: the turn at its yaw-rate limit plus the
            // controller's tail.
            let v_now = if m == Manoeuvre::BrakeThenTurnRight {
                6.0
            } else {
                v_turn
            };
            let dur = by.abs() / (a_lat / v_now).min(0.6) + 2.5;
            let mut turn = phase(
                dur,
                Long::Cruise {
                    v: None,
                    wobble: 0.0,
                    period: 5.0,
                },
                Lat::Turn { by, a_lat },
            );
            if signalled {
                turn.signal = signal_for(left);
            }
            ph.push(turn);
            ph.push(cruise(rng, 2.0, 4.0));
            (v0, ph)
        }
        Manoeuvre::LaneChangeLeft { signal } | Manoeuvre::LaneChangeRight { signal } => {
            let left = matches!(m, Manoeuvre::LaneChangeLeft { .. });
            let v0 = u(rng, 10.0, 25.0);
            let by = u(rng, 3.2, 3.8) * if left { 1.0 } else { -1.0 };
            let dur = u(rng, 3.0, 6.0);
            let pre = cruise(rng, 0.5, 1.5);
            let mut lead = cruise(rng, 1.0, 2.0);
            let mut change = phase(
                dur,
                Long::Cruise {
                    v: None,
                    wobble: 0.0,
                    period: 5.0,
                },
                Lat::Lane { by, dur },
            );
            if signal {
                lead.signal = signal_for(left);
                change.signal = signal_for(left);
            }
            let post = cruise(rng, 2.0, 4.0);
            (v0, vec![pre, lead, change, post])
        }
    }
}

/// Which columns a clip records.
struct Present {
    speed: bool,
    accel: bool,
    steering: bool,
    yaw: bool,
    pedals: bool,
    signal: bool,
}

fn columns(rng: &mut ChaCha8Rng, drop: bool) -> Present {
    if !drop {
        return Present {
            speed: true,
            accel: true,
            steering: true,
            yaw: true,
            pedals: true,
            signal: true,
        };
    }
    let accel = !rng.random_bool(0.3);
    let yaw = !rng.random_bool(0.3);
    let steering = !yaw || !rng.random_bool(0.3);
    Present {
        speed: !accel || !rng.random_bool(0.1),
        accel,
        steering,
        yaw,
        pedals: !rng.random_bool(0.3),
        signal: !rng.random_bool(0.2),
    }
}

/// Simulates clip `index` of manoeuvre `m` for `seed`.
pub fn scenario(m: Manoeuvre, seed: u64, index: u64, sim: &SimConfig) -> Scenario {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // One stream per (manoeuvre, clip): adding manoeuvres or clips leaves the others as they
    // were.
    rng.set_stream((m.index() << 32) | (index & 0xffff_ffff));
    let (v0, phases) = script(m, &mut rng);
    let veh = Vehicle {
        x: 0.0,
        y: 0.0,
        psi: u(&mut rng, -PI, PI),
        v: v0,
        a: 0.0,
        wheel_deg: 0.0,
        ratio: u(&mut rng, 14.0, 17.0),
        wheelbase: u(&mut rng, 2.6, 3.0),
    };
    let states = run(veh, &phases, &mut rng);
    let present = columns(&mut rng, sim.drop_columns);
    let rate = if sim.rate_hz > 0.0 { sim.rate_hz } else { 10.0 };
    let duration = states.len() as f64 * STEP_S;
    let n = (duration * rate).floor() as usize;
    let mut cols = Columns::default();
    let mut speed = Vec::with_capacity(n);
    let mut accel = Vec::with_capacity(n);
    let mut steering = Vec::with_capacity(n);
    let mut yaw = Vec::with_capacity(n);
    let mut brake = Vec::with_capacity(n);
    let mut throttle = Vec::with_capacity(n);
    let mut signal = Vec::with_capacity(n);
    for k in 0..n {
        let t_nominal = k as f64 / rate;
        let idx = ((t_nominal / STEP_S).round() as usize).min(states.len() - 1);
        let s = states[idx];
        let jitter = if k == 0 {
            0.0
        } else {
            u(&mut rng, -1.0, 1.0) * sim.jitter_s
        };
        cols.t_s.push(t_nominal + jitter);
        let cell = |rng: &mut ChaCha8Rng, v: f64| {
            (!rng.random_bool(sim.missing_share.clamp(0.0, 1.0))).then_some(v)
        };
        let v = if s.v < 0.01 {
            0.0
        } else {
            (s.v + sim.speed_sd_mps * normal(&mut rng)).clamp(0.0, 90.0)
        };
        speed.push(cell(&mut rng, v));
        let a = (s.a + sim.accel_sd_mps2 * normal(&mut rng)).clamp(-15.0, 15.0);
        accel.push(cell(&mut rng, a));
        let st = (s.wheel_deg + sim.steering_sd_deg * normal(&mut rng)).clamp(-900.0, 900.0);
        steering.push(cell(&mut rng, st));
        let y = (s.yaw_dps + sim.yaw_sd_dps * normal(&mut rng)).clamp(-180.0, 180.0);
        yaw.push(cell(&mut rng, y));
        let b = if s.brake > 0.0 {
            (s.brake + sim.pedal_sd * normal(&mut rng)).clamp(0.0, 1.0)
        } else {
            0.0
        };
        brake.push(cell(&mut rng, b));
        let th = (s.throttle + sim.pedal_sd * normal(&mut rng)).clamp(0.0, 1.0);
        throttle.push(cell(&mut rng, th));
        let missing_signal = rng.random_bool(sim.missing_share.clamp(0.0, 1.0));
        signal.push(if missing_signal { None } else { s.signal });
    }
    cols.speed_mps = present.speed.then_some(speed);
    cols.accel_mps2 = present.accel.then_some(accel);
    cols.steering_deg = present.steering.then_some(steering);
    cols.yaw_rate_dps = present.yaw.then_some(yaw);
    cols.brake = present.pedals.then_some(brake);
    cols.throttle = present.pedals.then_some(throttle);
    cols.turn_signal = present.signal.then_some(signal);
    // The simulator only writes in-range values at increasing times, so this cannot fail for
    // a sane SimConfig; a broken one (a negative rate, a jitter above half the sampling
    // period) gets a two-sample stationary track rather than a panic.
    let track = Track::from_columns(cols).unwrap_or_else(|_| fallback_track());
    Scenario {
        manoeuvre: m,
        seed,
        index,
        track,
        truth: m.truth().iter().map(|s| s.to_string()).collect(),
    }
}

fn fallback_track() -> Track {
    let cols = Columns {
        t_s: vec![0.0, 1.0],
        speed_mps: Some(vec![Some(0.0), Some(0.0)]),
        ..Columns::default()
    };
    match Track::from_columns(cols) {
        Ok(t) => t,
        // Two increasing in-range samples always validate.
        Err(e) => panic!("fallback track refused: {e}"),
    }
}

/// Per-label scores of the rules over simulated clips. Precision and recall count decided
/// (clip, label) pairs only — an undecided label is neither right nor wrong — and coverage is
/// the share of pairs decided.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelScore {
    pub label: String,
    pub clips: usize,
    pub decided: usize,
    pub true_pos: usize,
    pub false_pos: usize,
    pub true_neg: usize,
    pub false_neg: usize,
    /// `None` when nothing was called positive.
    pub precision: Option<f64>,
    /// `None` when no decided clip was truly positive.
    pub recall: Option<f64>,
    pub coverage: f64,
}

/// How a confusable manoeuvre group fared on the label it is confused with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Confusion {
    /// E.g. "lane change called turn".
    pub case: String,
    pub clips: usize,
    /// Wrongly called positive.
    pub confused: usize,
    /// Rightly called negative.
    pub rejected: usize,
    pub undecided: usize,
}

/// A wrong decision, for debugging the rules.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Mistake {
    pub manoeuvre: String,
    pub index: u64,
    pub label: String,
    pub truth: bool,
    pub confidence: f64,
    pub evidence: String,
}

/// The result of [`evaluate`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    pub n_per_manoeuvre: usize,
    pub seed: u64,
    pub clips: usize,
    pub labels: Vec<LabelScore>,
    pub confusions: Vec<Confusion>,
    /// The first 50 wrong decisions.
    pub mistakes: Vec<Mistake>,
}

impl Report {
    pub fn label(&self, label: &str) -> Option<&LabelScore> {
        self.labels.iter().find(|l| l.label == label)
    }
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let opt = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.3}"));
        writeln!(
            f,
            "kinematic rules on {} simulated clips ({} per manoeuvre, seed {})",
            self.clips, self.n_per_manoeuvre, self.seed
        )?;
        writeln!(
            f,
            "{:<11} {:>9} {:>7} {:>8} {:>5} {:>4} {:>5} {:>4}",
            "label", "precision", "recall", "coverage", "tp", "fp", "tn", "fn"
        )?;
        for l in &self.labels {
            writeln!(
                f,
                "{:<11} {:>9} {:>7} {:>8.3} {:>5} {:>4} {:>5} {:>4}",
                l.label,
                opt(l.precision),
                opt(l.recall),
                l.coverage,
                l.true_pos,
                l.false_pos,
                l.true_neg,
                l.false_neg
            )?;
        }
        writeln!(f, "confusable cases:")?;
        writeln!(
            f,
            "{:<32} {:>5} {:>8} {:>8} {:>9}",
            "case", "clips", "confused", "rejected", "undecided"
        )?;
        for c in &self.confusions {
            writeln!(
                f,
                "{:<32} {:>5} {:>8} {:>8} {:>9}",
                c.case, c.clips, c.confused, c.rejected, c.undecided
            )?;
        }
        Ok(())
    }
}

/// Simulates `n_per_manoeuvre` clips of every [`Manoeuvre`] with [`SimConfig::realistic`]
/// and scores [`annotate`] with `cfg` against the truth.
pub fn evaluate(n_per_manoeuvre: usize, seed: u64, cfg: &AnnotateConfig) -> Report {
    evaluate_with(n_per_manoeuvre, seed, cfg, &SimConfig::realistic())
}

/// [`evaluate`] with explicit sensor settings.
pub fn evaluate_with(
    n_per_manoeuvre: usize,
    seed: u64,
    cfg: &AnnotateConfig,
    sim: &SimConfig,
) -> Report {
    #[derive(Default, Clone, Copy)]
    struct Count {
        clips: usize,
        tp: usize,
        fp: usize,
        tn: usize,
        fn_: usize,
    }
    let mut counts = [Count::default(); LABELS.len()];
    // (case, manoeuvre filter, labels confused with)
    type Filter = fn(Manoeuvre) -> bool;
    let cases: [(&str, Filter, &[&str]); 4] = [
        (
            "lane change called turn",
            |m| {
                matches!(
                    m,
                    Manoeuvre::LaneChangeLeft { .. } | Manoeuvre::LaneChangeRight { .. }
                )
            },
            &["turn_left", "turn_right"],
        ),
        (
            "turn called merge",
            |m| {
                matches!(
                    m,
                    Manoeuvre::TurnLeft | Manoeuvre::TurnRight | Manoeuvre::BrakeThenTurnRight
                )
            },
            &["merge"],
        ),
        ("coast called brake", |m| m == Manoeuvre::Coast, &["brake"]),
        ("creep called stop", |m| m == Manoeuvre::Creep, &["stop"]),
    ];
    let mut conf: Vec<Confusion> = cases
        .iter()
        .map(|(name, _, _)| Confusion {
            case: name.to_string(),
            clips: 0,
            confused: 0,
            rejected: 0,
            undecided: 0,
        })
        .collect();
    let mut mistakes = Vec::new();
    let mut clips = 0;
    for m in Manoeuvre::ALL {
        for k in 0..n_per_manoeuvre as u64 {
            let sc = scenario(m, seed, k, sim);
            let ann = annotate(&sc.track, None, cfg);
            clips += 1;
            for (li, label) in LABELS.iter().enumerate() {
                let truth = m.truth().contains(label);
                let c = &mut counts[li];
                c.clips += 1;
                if let Some(d) = ann.get(label) {
                    match (d.value, truth) {
                        (true, true) => c.tp += 1,
                        (true, false) => c.fp += 1,
                        (false, false) => c.tn += 1,
                        (false, true) => c.fn_ += 1,
                    }
                    if d.value != truth && mistakes.len() < 50 {
                        mistakes.push(Mistake {
                            manoeuvre: m.name().to_string(),
                            index: k,
                            label: label.to_string(),
                            truth,
                            confidence: d.confidence,
                            evidence: d
                                .evidence
                                .iter()
                                .map(|e| format!("{}: {}", e.signal, e.note))
                                .collect::<Vec<_>>()
                                .join("; "),
                        });
                    }
                }
            }
            for (ci, (_, filter, labels)) in cases.iter().enumerate() {
                if !filter(m) {
                    continue;
                }
                let c = &mut conf[ci];
                c.clips += 1;
                let vals: Vec<Option<bool>> = labels.iter().map(|l| ann.value(l)).collect();
                if vals.contains(&Some(true)) {
                    c.confused += 1;
                } else if vals.iter().all(|v| *v == Some(false)) {
                    c.rejected += 1;
                } else {
                    c.undecided += 1;
                }
            }
        }
    }
    let labels = LABELS
        .iter()
        .zip(counts)
        .map(|(label, c)| {
            let decided = c.tp + c.fp + c.tn + c.fn_;
            LabelScore {
                label: label.to_string(),
                clips: c.clips,
                decided,
                true_pos: c.tp,
                false_pos: c.fp,
                true_neg: c.tn,
                false_neg: c.fn_,
                precision: (c.tp + c.fp > 0).then(|| c.tp as f64 / (c.tp + c.fp) as f64),
                recall: (c.tp + c.fn_ > 0).then(|| c.tp as f64 / (c.tp + c.fn_) as f64),
                coverage: if c.clips == 0 {
                    0.0
                } else {
                    decided as f64 / c.clips as f64
                },
            }
        })
        .collect();
    Report {
        n_per_manoeuvre,
        seed,
        clips,
        labels,
        confusions: conf,
        mistakes,
    }
}

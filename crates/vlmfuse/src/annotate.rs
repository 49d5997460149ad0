//! `vlmfuse annotate FILE|-`: the kinematic rules on one vehicle-signal track, with the evidence
//! for every label they decide and the reason for every label they leave unknown, exactly as
//! the service derives them from a `signals` part (`[annotate]` of the same configuration).
//! `--simulate N` scores the rules instead on N simulated clips per manoeuvre (a kinematic
//! bicycle model with sensor noise): per-label precision, recall and coverage, and the
//! confusable cases.

use crate::config::{Config, ServeArgs};
use anyhow::{bail, Context};
use clap::Args;
use std::io::Read;
use std::path::PathBuf;
use vlmfuse_annotate::{annotate, sim, Annotation, Track};

#[derive(Args, Debug, Clone)]
pub struct AnnotateArgs {
    /// The signal track: CSV with a header or JSON lines (`t_s`, `speed_mps`, `accel_mps2`,
    /// `steering_deg`, `yaw_rate_dps`, `brake`, `throttle`, `turn_signal`), or `-` for
    /// standard input.
    #[arg(required_unless_present = "simulate")]
    pub input: Option<PathBuf>,
    /// Print the annotation as JSON (the `derived` object of `/v1/infer`'s answer).
    #[arg(long)]
    pub json: bool,
    /// Annotate only `START,END` seconds of the track.
    #[arg(long, value_parser = parse_window)]
    pub window: Option<(f64, f64)>,
    /// The clip's duration in seconds: the track must cover `[0, duration]` (within
    /// `[annotate] cover_tolerance_s`), as the service checks.
    #[arg(long)]
    pub duration: Option<f64>,
    /// Instead of a track: score the rules on this many simulated clips per manoeuvre.
    #[arg(long, conflicts_with = "input")]
    pub simulate: Option<usize>,
    /// Seed of the simulation.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Sensor noise of the simulation, as a multiple of the default (speed 0.05 m/s,
    /// acceleration 0.15 m/s², steering 1°, yaw rate 0.5 °/s, pedals 0.01).
    #[arg(long, default_value_t = 1.0, requires = "simulate")]
    pub noise: f64,
    /// Share of the simulated tracks' cells left empty (dropped samples).
    #[arg(long, default_value_t = 0.02, requires = "simulate")]
    pub missing: f64,
    /// TOML configuration whose `[annotate]` is used, as `vlmfuse serve --config`.
    #[arg(long, env = "VLMFUSE_CONFIG")]
    pub config: Option<PathBuf>,
}

fn parse_window(s: &str) -> Result<(f64, f64), String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?}: expected START,END in seconds"))?;
    let num = |x: &str| {
        x.trim()
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| format!("{x:?} is not a number of seconds"))
    };
    let (a, b) = (num(a)?, num(b)?);
    if a >= b {
        return Err(format!(
            "the window {a},{b} is empty: START must be below END"
        ));
    }
    Ok((a, b))
}

pub fn run(args: AnnotateArgs) -> anyhow::Result<()> {
    // The configuration `serve` would run with: the file (or defaults), then its variables.
    let mut argv = vec!["serve".to_string()];
    if let Some(p) = &args.config {
        argv.push("--config".into());
        argv.push(p.display().to_string());
    }
    let cfg = Config::load(&ServeArgs::try_parse_from(argv)?)?;
    let section = &cfg.annotate;
    if let Some(n) = args.simulate {
        if n == 0 {
            bail!("--simulate needs at least 1 clip per manoeuvre");
        }
        if !(args.noise.is_finite() && args.noise >= 0.0) {
            bail!("--noise must be a multiple >= 0, got {}", args.noise);
        }
        if !(0.0..1.0).contains(&args.missing) {
            bail!("--missing must be a share in [0, 1), got {}", args.missing);
        }
        let base = sim::SimConfig::realistic();
        let simcfg = sim::SimConfig {
            speed_sd_mps: base.speed_sd_mps * args.noise,
            accel_sd_mps2: base.accel_sd_mps2 * args.noise,
            steering_sd_deg: base.steering_sd_deg * args.noise,
            yaw_sd_dps: base.yaw_sd_dps * args.noise,
            pedal_sd: base.pedal_sd * args.noise,
            missing_share: args.missing,
            ..base
        };
        let report = sim::evaluate_with(n, args.seed, &section.rules, &simcfg);
        if args.json {
            println!("{}", serde_json::to_string_pretty(&report)?);
        } else {
            print!("{report}");
        }
        return Ok(());
    }
    let input = args.input.as_ref().expect("clap requires it");
    let bytes = read_bounded(input, section.max_bytes)?;
    let name = if input.as_os_str() == "-" {
        "<stdin>".to_string()
    } else {
        input.display().to_string()
    };
    let track = Track::parse_with(&bytes, &section.limits())
        .map_err(|e| anyhow::anyhow!("{name}: {e} ({})", e.kind()))?;
    if let Some(d) = args.duration {
        track
            .covers_duration(d, section.cover_tolerance_s)
            .map_err(|e| anyhow::anyhow!("{name}: {e}"))?;
    }
    let a = annotate(&track, args.window, &section.rules);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&a)?);
    } else {
        print!("{}", listing(&name, &a));
    }
    Ok(())
}

/// Reads at most `max` bytes: a track is read whole, so its size is bounded as the service's.
fn read_bounded(input: &PathBuf, max: u64) -> anyhow::Result<Vec<u8>> {
    let mut buf = Vec::new();
    let read = if input.as_os_str() == "-" {
        std::io::stdin().take(max + 1).read_to_end(&mut buf)
    } else {
        std::fs::File::open(input)
            .with_context(|| format!("cannot open {}", input.display()))?
            .take(max + 1)
            .read_to_end(&mut buf)
    };
    read.with_context(|| format!("cannot read {}", input.display()))?;
    if buf.len() as u64 > max {
        bail!(
            "{} is larger than [annotate] max_bytes = {max} bytes",
            input.display()
        );
    }
    Ok(buf)
}

/// The readable form: one line per decided label with its evidence, then the unknown ones.
fn listing(name: &str, a: &Annotation) -> String {
    let mut out = format!(
        "{name}: {} samples, {:.2}-{:.2} s\n",
        a.samples, a.start_s, a.end_s
    );
    for d in &a.labels {
        out.push_str(&format!(
            "  {:<11} {:<3} confidence {:.2}\n",
            d.label,
            if d.value { "yes" } else { "no" },
            d.confidence
        ));
        for e in &d.evidence {
            out.push_str(&format!(
                "      {} = {:.3} at {:.2} s (threshold {:.3}, margin {:+.3}) {}\n",
                e.signal, e.value, e.t_s, e.threshold, e.margin, e.note
            ));
        }
    }
    for u in &a.undecided {
        out.push_str(&format!("  {:<11} unknown: {}\n", u.label, u.reason));
    }
    out
}

//! The charts `eval --plots` writes, as SVG (plotters' SVG backend needs no system fonts, so the
//! charts render the same on a bare CI machine as on a laptop).

use crate::eval::{CurveRun, EvalRun, Pick, CURVE_METHODS};
use plotters::coord::ranged1d::SegmentValue;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use vlmfuse_fusion::metrics::Scores;

const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];

/// plotters' errors borrow the backend, so they are flattened to text with the file named.
fn err<E: std::fmt::Display>(path: &Path) -> impl Fn(E) -> anyhow::Error + '_ {
    move |e| anyhow::anyhow!("{}: {e}", path.display())
}

/// Writes every chart into `dir` and returns their paths.
pub fn write_all(dir: &Path, run: &EvalRun) -> anyhow::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).map_err(err(dir))?;
    let files = vec![
        reputations(&dir.join("reputations.svg"), run)?,
        reliability(&dir.join("reliability.svg"), run)?,
        ablations(&dir.join("ablations.svg"), run)?,
    ];
    Ok(files)
}

/// Reputation of every reporter after each round, with the end of the history marked.
fn reputations(path: &Path, run: &EvalRun) -> anyhow::Result<PathBuf> {
    let names = run.engine.reporters();
    let n = run.outcomes.len();
    let ymax = run
        .outcomes
        .iter()
        .flat_map(|o| o.w_after.iter().copied())
        .fold(0.0f64, f64::max)
        .max(1.0 / names.len() as f64)
        * 1.15;
    let root = SVGBackend::new(path, (960, 540)).into_drawing_area();
    root.fill(&WHITE).map_err(err(path))?;
    let mut chart = ChartBuilder::on(&root)
        .caption("Reputation w after each round", ("sans-serif", 24))
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..n.max(1) as f64, 0f64..ymax.min(1.0))
        .map_err(err(path))?;
    chart
        .configure_mesh()
        .x_desc("round (file order)")
        .x_label_formatter(&|x| format!("{x:.0}"))
        .y_desc("reputation w")
        .draw()
        .map_err(err(path))?;
    for (i, name) in names.iter().enumerate() {
        let color = PALETTE[i % PALETTE.len()];
        chart
            .draw_series(LineSeries::new(
                run.outcomes
                    .iter()
                    .enumerate()
                    .map(|(t, o)| (t as f64 + 1.0, o.w_after[i])),
                color.stroke_width(2),
            ))
            .map_err(err(path))?
            .label(name.as_str())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
    }
    let h = run.n_hist as f64;
    chart
        .draw_series(LineSeries::new(
            vec![(h, 0.0), (h, ymax.min(1.0))],
            BLACK.mix(0.5).stroke_width(1),
        ))
        .map_err(err(path))?
        .label("end of history")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.mix(0.5)));
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(err(path))?;
    root.present().map_err(err(path))?;
    Ok(path.to_path_buf())
}

/// Reliability diagram of the fused posteriors on the scored rounds (10 equal-width bins).
fn reliability(path: &Path, run: &EvalRun) -> anyhow::Result<PathBuf> {
    let title = format!(
        "Reliability of fused posteriors, {} (ECE {:.4})",
        run.engine.method(),
        run.rows[0].scores.ece
    );
    reliability_diagram(path, &title, &run.rows[0].scores)
}

fn reliability_diagram(path: &Path, title: &str, scores: &Scores) -> anyhow::Result<PathBuf> {
    let root = SVGBackend::new(path, (640, 640)).into_drawing_area();
    root.fill(&WHITE).map_err(err(path))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d(0f64..1f64, 0f64..1f64)
        .map_err(err(path))?;
    chart
        .configure_mesh()
        .x_desc("mean predicted probability")
        .y_desc("observed frequency")
        .draw()
        .map_err(err(path))?;
    chart
        .draw_series(LineSeries::new(
            vec![(0.0, 0.0), (1.0, 1.0)],
            BLACK.mix(0.4),
        ))
        .map_err(err(path))?
        .label("perfect calibration")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.mix(0.4)));
    let total: u64 = scores.reliability.iter().map(|b| b.count).sum();
    let blue = PALETTE[0];
    chart
        .draw_series(scores.reliability.iter().filter(|b| b.count > 0).map(|b| {
            Rectangle::new(
                [(b.lo + 0.01, 0.0), (b.hi - 0.01, b.observed)],
                blue.mix(0.35).filled(),
            )
        }))
        .map_err(err(path))?
        .label("observed per bin")
        .legend(move |(x, y)| {
            Rectangle::new([(x, y - 5), (x + 20, y + 5)], blue.mix(0.35).filled())
        });
    chart
        .draw_series(scores.reliability.iter().filter(|b| b.count > 0).map(|b| {
            let r = 3.0 + 9.0 * (b.count as f64 / total.max(1) as f64).sqrt();
            Circle::new(
                (b.mean_predicted, b.observed),
                r as i32,
                PALETTE[3].filled(),
            )
        }))
        .map_err(err(path))?
        .label("(mean predicted, observed); area ~ count")
        .legend(|(x, y)| Circle::new((x + 10, y), 4, PALETTE[3].filled()));
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(err(path))?;
    root.present().map_err(err(path))?;
    Ok(path.to_path_buf())
}

/// Reads one metric off a row's scores.
type Metric = fn(&vlmfuse_fusion::metrics::Scores) -> f64;

/// Hamming, micro-F1 and macro-F1 of every row, side by side, like the paper's ablation figure.
fn ablations(path: &Path, run: &EvalRun) -> anyhow::Result<PathBuf> {
    let rows = &run.rows;
    let r = rows.len() as i32;
    let height = 140 + 34 * rows.len() as u32;
    let root = SVGBackend::new(path, (1200, height)).into_drawing_area();
    root.fill(&WHITE).map_err(err(path))?;
    let root = root
        .titled(
            "Method, ablations and baselines on the scored rounds",
            ("sans-serif", 24),
        )
        .map_err(err(path))?;
    let panels = root.split_by_breakpoints([520, 747, 974], [] as [u32; 0]);
    let metrics: [(&str, Metric); 3] = [
        ("Hamming (lower is better)", |s| s.hamming),
        ("micro-F1", |s| s.micro_f1),
        ("macro-F1", |s| s.macro_f1),
    ];
    let names: Vec<String> = rows.iter().map(|r| r.name.clone()).collect();
    for (p, (title, get)) in metrics.iter().enumerate() {
        let area = &panels[p];
        let xmax = rows
            .iter()
            .map(|r| get(&r.scores))
            .fold(0.0f64, f64::max)
            .max(0.05)
            * 1.1;
        let mut chart = ChartBuilder::on(area)
            .caption(*title, ("sans-serif", 18))
            .margin(8)
            .x_label_area_size(30)
            .y_label_area_size(if p == 0 { 290 } else { 4 })
            .build_cartesian_2d(0f64..xmax, (0..r).into_segmented())
            .map_err(err(path))?;
        let names_ref = &names;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .x_labels(4)
            .y_labels(rows.len())
            .y_label_formatter(&|v| match v {
                SegmentValue::CenterOf(i) if p == 0 => names_ref
                    .get((r - 1 - *i) as usize)
                    .cloned()
                    .unwrap_or_default(),
                _ => String::new(),
            })
            .draw()
            .map_err(err(path))?;
        chart
            .draw_series(rows.iter().enumerate().map(|(i, row)| {
                let y = r - 1 - i as i32;
                let color = match row.kind {
                    "method" => PALETTE[0],
                    "ablation" => PALETTE[1],
                    _ => PALETTE[7],
                };
                let mut bar = Rectangle::new(
                    [
                        (0.0, SegmentValue::Exact(y)),
                        (get(&row.scores), SegmentValue::Exact(y + 1)),
                    ],
                    color.filled(),
                );
                bar.set_margin(5, 5, 0, 0);
                bar
            }))
            .map_err(err(path))?;
    }
    root.present().map_err(err(path))?;
    Ok(path.to_path_buf())
}

/// The learning curve (`eval --curve`): Hamming, micro-F1 and macro-F1 of each method against
/// the number of labelled history rounds, with the label-free baselines as horizontal lines; and
/// a reliability diagram per method at the curve's last point.
pub fn write_curve(dir: &Path, c: &CurveRun) -> anyhow::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).map_err(err(dir))?;
    let mut files = vec![curve(&dir.join("curve.svg"), c)?];
    for m in CURVE_METHODS {
        if let Some(p) = c
            .points
            .iter()
            .rev()
            .find(|p| p.method == m && (!c.compare || p.pick == Pick::Review))
        {
            let title = format!(
                "Reliability, {m}, {} labelled (ECE {:.4})",
                p.labelled, p.scores.ece
            );
            files.push(reliability_diagram(
                &dir.join(format!("reliability-{m}.svg")),
                &title,
                &p.scores,
            )?);
        }
    }
    Ok(files)
}

fn curve(path: &Path, c: &CurveRun) -> anyhow::Result<PathBuf> {
    // The N of the curve in the order asked, as categories (0 and 1,269 on one axis).
    let mut ns: Vec<usize> = Vec::new();
    for p in &c.points {
        if !ns.contains(&p.labelled) {
            ns.push(p.labelled);
        }
    }
    let root = SVGBackend::new(path, (1500, 520)).into_drawing_area();
    root.fill(&WHITE).map_err(err(path))?;
    let root = root
        .titled(
            &format!(
                "Learning curve: scored rounds vs labelled history rounds (seed {}{})",
                c.seed,
                if c.frozen { ", frozen" } else { "" }
            ),
            ("sans-serif", 22),
        )
        .map_err(err(path))?;
    let panels = root.split_evenly((1, 3));
    let metrics: [(&str, Metric, bool); 3] = [
        ("Hamming (lower is better)", |s| s.hamming, false),
        ("micro-F1", |s| s.micro_f1, true),
        ("macro-F1", |s| s.macro_f1, true),
    ];
    let mv = c
        .baselines
        .iter()
        .find(|b| b.name.ends_with("majority vote"));
    let ds = c.baselines.iter().find(|b| b.name.contains("Dawid-Skene"));
    for (panel, (title, get, higher)) in panels.iter().zip(metrics) {
        let mut vals: Vec<f64> = c.points.iter().map(|p| get(&p.scores)).collect();
        vals.extend(c.baselines.iter().map(|b| get(&b.scores)));
        let lo = vals.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = vals.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let pad = ((hi - lo) * 0.08).max(0.01);
        let mut chart = ChartBuilder::on(panel)
            .caption(title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(52)
            .build_cartesian_2d(-0.3f64..(ns.len() as f64 - 0.7), (lo - pad)..(hi + pad))
            .map_err(err(path))?;
        let ns_ref = &ns;
        chart
            .configure_mesh()
            .x_labels(ns.len())
            .x_label_formatter(&|x| {
                let i = x.round();
                if (x - i).abs() < 1e-6 && i >= 0.0 && (i as usize) < ns_ref.len() {
                    ns_ref[i as usize].to_string()
                } else {
                    String::new()
                }
            })
            .x_desc("labelled history rounds")
            .draw()
            .map_err(err(path))?;
        let xmax = ns.len() as f64 - 0.7;
        let mut hline = |name: String, v: f64, color: RGBColor| -> anyhow::Result<()> {
            chart
                .draw_series(LineSeries::new(
                    vec![(-0.3, v), (xmax, v)],
                    color.stroke_width(2),
                ))
                .map_err(err(path))?
                .label(name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            Ok(())
        };
        if let Some(b) = mv {
            hline("majority vote".into(), get(&b.scores), PALETTE[7])?;
        }
        if let Some(b) = ds {
            hline("Dawid-Skene (no labels)".into(), get(&b.scores), PALETTE[4])?;
        }
        let best = c
            .baselines
            .iter()
            .filter(|b| b.name.ends_with(" alone"))
            .max_by(|a, b| {
                let (x, y) = (get(&a.scores), get(&b.scores));
                if higher {
                    x.total_cmp(&y)
                } else {
                    y.total_cmp(&x)
                }
            });
        if let Some(b) = best {
            hline(
                format!(
                    "best reporter ({})",
                    b.name.trim_start_matches("baseline: ")
                ),
                get(&b.scores),
                PALETTE[5],
            )?;
        }
        for (mi, m) in CURVE_METHODS.iter().enumerate() {
            let color = PALETTE[mi * 3 % PALETTE.len()];
            // With `--pick compare`, the queue's picks solid and random picks dashed.
            let picks: &[Pick] = if c.compare {
                &[Pick::Review, Pick::Random]
            } else {
                &[Pick::Random]
            };
            for &pick in picks {
                let pts: Vec<(f64, f64)> = c
                    .points
                    .iter()
                    .filter(|p| p.method == *m && (!c.compare || p.pick == pick))
                    .map(|p| {
                        let x = ns.iter().position(|&n| n == p.labelled).unwrap_or(0) as f64;
                        (x, get(&p.scores))
                    })
                    .collect();
                let name = if c.compare {
                    format!("{} ({} picks)", m.name(), pick.name())
                } else {
                    m.name().to_string()
                };
                if pick == Pick::Random && c.compare {
                    chart
                        .draw_series(DashedLineSeries::new(
                            pts.clone(),
                            10,
                            6,
                            color.stroke_width(2),
                        ))
                        .map_err(err(path))?
                        .label(name)
                        .legend(move |(x, y)| {
                            PathElement::new(vec![(x, y), (x + 8, y)], color.stroke_width(2))
                        });
                    chart
                        .draw_series(
                            pts.iter()
                                .map(|&p| TriangleMarker::new(p, 5, color.filled())),
                        )
                        .map_err(err(path))?;
                } else {
                    chart
                        .draw_series(LineSeries::new(pts.clone(), color.stroke_width(3)))
                        .map_err(err(path))?
                        .label(name)
                        .legend(move |(x, y)| {
                            PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(3))
                        });
                    chart
                        .draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled())))
                        .map_err(err(path))?;
                }
            }
        }
        chart
            .configure_series_labels()
            .position(if higher {
                SeriesLabelPosition::LowerRight
            } else {
                SeriesLabelPosition::UpperRight
            })
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 12))
            .draw()
            .map_err(err(path))?;
    }
    root.present().map_err(err(path))?;
    Ok(path.to_path_buf())
}

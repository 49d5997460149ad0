//! A vehicle-signal track: timestamped samples of speed, acceleration, steering, yaw rate,
//! pedals and turn signal, parsed from CSV or JSON lines held in memory.
//!
//! Why so strict: the labels derived from a track go into the same fusion as the models'
//! answers, where a wrong "kinematic" label weighs like ground truth. A track with a clock that
//! runs backwards, a NaN, or a speed of 300 m/s is a broken recording, and annotating it would
//! turn a recording bug into confident labels. So every such track is refused, with the line and
//! the column, rather than repaired.
//!
//! Columns (all but `t_s` optional; a column absent from the whole input is `None` for the
//! track, a missing cell inside a present column is a missing sample):
//!
//! | column         | unit / values              | valid range     |
//! |----------------|----------------------------|-----------------|
//! | `t_s`          | seconds (clip or day time) | 0 ..= 86 400    |
//! | `speed_mps`    | m/s, ground speed          | 0 ..= 90        |
//! | `accel_mps2`   | m/s², longitudinal         | -15 ..= 15      |
//! | `steering_deg` | steering-*wheel* angle, °  | -900 ..= 900    |
//! | `yaw_rate_dps` | °/s                        | -180 ..= 180    |
//! | `brake`        | pedal position             | 0 ..= 1         |
//! | `throttle`     | pedal position             | 0 ..= 1         |
//! | `turn_signal`  | `left`, `right`, `none`    |                 |
//!
//! Sign convention (ISO 8855 / right-hand, z up): positive yaw rate and positive steering are
//! to the **left** (counter-clockwise seen from above).
//!
//! Format detection: JSON lines when the first non-whitespace byte is `{`, otherwise CSV with
//! a header row. No I/O here: the caller reads the bytes and bounds their size; this module
//! bounds the sample count ([`TrackLimits::max_samples`]) so the work stays bounded for any
//! input.

use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

/// The column names, in the order [`Track::to_csv`] writes them.
pub const COLUMNS: [&str; 8] = [
    "t_s",
    "speed_mps",
    "accel_mps2",
    "steering_deg",
    "yaw_rate_dps",
    "brake",
    "throttle",
    "turn_signal",
];

/// Physical ranges: wider than any road vehicle reaches, so only broken recordings fall
/// outside. `(column, min, max)`.
const RANGES: [(&str, f64, f64); 7] = [
    ("t_s", 0.0, 86_400.0),
    ("speed_mps", 0.0, 90.0),
    ("accel_mps2", -15.0, 15.0),
    ("steering_deg", -900.0, 900.0),
    ("yaw_rate_dps", -180.0, 180.0),
    ("brake", 0.0, 1.0),
    ("throttle", 0.0, 1.0),
];

/// The state of the direction indicator at one sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TurnSignal {
    None,
    Left,
    Right,
}

impl TurnSignal {
    /// The wire name (`left`, `right`, `none`).
    pub fn as_str(self) -> &'static str {
        match self {
            TurnSignal::None => "none",
            TurnSignal::Left => "left",
            TurnSignal::Right => "right",
        }
    }

    /// Case-insensitive; `None` for anything but the three names.
    pub fn parse(s: &str) -> Option<TurnSignal> {
        match s.trim().to_ascii_lowercase().as_str() {
            "none" => Some(TurnSignal::None),
            "left" => Some(TurnSignal::Left),
            "right" => Some(TurnSignal::Right),
            _ => None,
        }
    }
}

/// A per-sample column: `None` for the whole column when the input lacks it, `Some(None)` at a
/// sample whose cell is empty (CSV) or `null` (JSON).
pub type Column<T> = Option<Vec<Option<T>>>;

/// The raw columns of a track, before validation. Every present column has exactly
/// `t_s.len()` entries. Public so that a simulator or a caller with its own decoder can build
/// a [`Track`] through [`Track::from_columns`], which applies the same checks as parsing.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Columns {
    pub t_s: Vec<f64>,
    pub speed_mps: Column<f64>,
    pub accel_mps2: Column<f64>,
    pub steering_deg: Column<f64>,
    pub yaw_rate_dps: Column<f64>,
    pub brake: Column<f64>,
    pub throttle: Column<f64>,
    pub turn_signal: Column<TurnSignal>,
}

impl Columns {
    /// The numeric columns other than `t_s`, by name, in [`COLUMNS`] order.
    fn numeric(&self) -> [(&'static str, &Column<f64>); 6] {
        [
            ("speed_mps", &self.speed_mps),
            ("accel_mps2", &self.accel_mps2),
            ("steering_deg", &self.steering_deg),
            ("yaw_rate_dps", &self.yaw_rate_dps),
            ("brake", &self.brake),
            ("throttle", &self.throttle),
        ]
    }

    fn numeric_mut(&mut self, name: &str) -> Option<&mut Column<f64>> {
        Some(match name {
            "speed_mps" => &mut self.speed_mps,
            "accel_mps2" => &mut self.accel_mps2,
            "steering_deg" => &mut self.steering_deg,
            "yaw_rate_dps" => &mut self.yaw_rate_dps,
            "brake" => &mut self.brake,
            "throttle" => &mut self.throttle,
            _ => return None,
        })
    }
}

/// Bounds on the work one track may cause.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackLimits {
    /// Most samples accepted. Parsing stops at the first sample past it, so a huge input costs
    /// no more than a track of this size (the byte limit is the caller's).
    pub max_samples: usize,
}

impl Default for TrackLimits {
    fn default() -> Self {
        // A 10 Hz recording of 2 h 46 min; clips are seconds to minutes.
        TrackLimits {
            max_samples: 100_000,
        }
    }
}

/// Why a track was refused. `line` is 1-based: the input line for parsed text (the CSV header
/// is line 1, so the first sample is line 2 when there are no blank lines), or the sample
/// number for [`Track::from_columns`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrackError {
    #[error("line {line}: {message}")]
    Parse {
        line: usize,
        column: Option<String>,
        message: String,
    },
    #[error("line {line}: unknown column `{column}` (known: {})", COLUMNS.join(", "))]
    UnknownColumn { line: usize, column: String },
    #[error("line {line}: required column `{column}` is missing")]
    MissingColumn { line: usize, column: String },
    #[error("a track needs at least 2 samples, this one has {samples}")]
    Empty { samples: usize },
    #[error("line {line}: more than {limit} samples")]
    TooManySamples { line: usize, limit: usize },
    #[error(
        "line {line}: t_s = {t_s} does not come after the previous sample's {previous} \
         (time must strictly increase)"
    )]
    NonMonotonicTime {
        line: usize,
        t_s: f64,
        previous: f64,
    },
    #[error("line {line}: `{column}` is not a finite number ({value})")]
    NonFinite {
        line: usize,
        column: String,
        value: f64,
    },
    #[error("line {line}: `{column}` = {value} is outside the physical range [{min}, {max}]")]
    OutOfRange {
        line: usize,
        column: String,
        value: f64,
        min: f64,
        max: f64,
    },
    #[error(
        "the track spans {track_start_s} s to {track_end_s} s and does not cover \
         {start_s} s to {end_s} s (tolerance {tolerance_s} s)"
    )]
    DoesNotCover {
        start_s: f64,
        end_s: f64,
        track_start_s: f64,
        track_end_s: f64,
        tolerance_s: f64,
    },
}

impl TrackError {
    /// A short machine name for the error, stable for API payloads and metrics.
    pub fn kind(&self) -> &'static str {
        match self {
            TrackError::Parse { .. } => "parse",
            TrackError::UnknownColumn { .. } => "unknown_column",
            TrackError::MissingColumn { .. } => "missing_column",
            TrackError::Empty { .. } => "empty",
            TrackError::TooManySamples { .. } => "too_many_samples",
            TrackError::NonMonotonicTime { .. } => "non_monotonic_time",
            TrackError::NonFinite { .. } => "non_finite",
            TrackError::OutOfRange { .. } => "out_of_range",
            TrackError::DoesNotCover { .. } => "does_not_cover",
        }
    }

    /// The column the error is about, where it has one.
    pub fn column(&self) -> Option<&str> {
        match self {
            TrackError::Parse { column, .. } => column.as_deref(),
            TrackError::UnknownColumn { column, .. }
            | TrackError::MissingColumn { column, .. }
            | TrackError::NonFinite { column, .. }
            | TrackError::OutOfRange { column, .. } => Some(column),
            TrackError::NonMonotonicTime { .. } => Some("t_s"),
            TrackError::Empty { .. }
            | TrackError::TooManySamples { .. }
            | TrackError::DoesNotCover { .. } => None,
        }
    }
}

/// A validated track: at least 2 samples, strictly increasing time, every value finite and in
/// its physical range. Immutable, so every holder can rely on that.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(transparent)]
pub struct Track {
    cols: Columns,
}

impl Track {
    /// Parses CSV or JSON lines (detected from the first non-whitespace byte) with the default
    /// [`TrackLimits`].
    pub fn parse(bytes: &[u8]) -> Result<Track, TrackError> {
        Track::parse_with(bytes, &TrackLimits::default())
    }

    /// [`Track::parse`] with explicit limits.
    pub fn parse_with(bytes: &[u8], limits: &TrackLimits) -> Result<Track, TrackError> {
        let text = std::str::from_utf8(bytes).map_err(|e| {
            let line = 1 + bytes[..e.valid_up_to()]
                .iter()
                .filter(|&&b| b == b'\n')
                .count();
            TrackError::Parse {
                line,
                column: None,
                message: format!("not UTF-8 text ({e})"),
            }
        })?;
        Track::parse_str_with(text, limits)
    }

    /// [`Track::parse`] for text already decoded.
    pub fn parse_str(text: &str) -> Result<Track, TrackError> {
        Track::parse_str_with(text, &TrackLimits::default())
    }

    /// [`Track::parse_str`] with explicit limits.
    pub fn parse_str_with(text: &str, limits: &TrackLimits) -> Result<Track, TrackError> {
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        let (cols, lines) = if text.trim_start().starts_with('{') {
            parse_jsonl(text, limits)?
        } else {
            parse_csv(text, limits)?
        };
        validate(&cols, limits, |i| lines[i]).map(|()| Track { cols })
    }

    /// Validates columns built elsewhere (the simulator, another decoder). Errors name the
    /// 1-based sample number as `line`.
    pub fn from_columns(cols: Columns) -> Result<Track, TrackError> {
        Track::from_columns_with(cols, &TrackLimits::default())
    }

    /// [`Track::from_columns`] with explicit limits.
    pub fn from_columns_with(cols: Columns, limits: &TrackLimits) -> Result<Track, TrackError> {
        let n = cols.t_s.len();
        if n > limits.max_samples {
            return Err(TrackError::TooManySamples {
                line: limits.max_samples + 1,
                limit: limits.max_samples,
            });
        }
        for (name, col) in cols.numeric() {
            if let Some(c) = col {
                if c.len() != n {
                    return Err(length_mismatch(name, c.len(), n));
                }
            }
        }
        if let Some(c) = &cols.turn_signal {
            if c.len() != n {
                return Err(length_mismatch("turn_signal", c.len(), n));
            }
        }
        validate(&cols, limits, |i| i + 1).map(|()| Track { cols })
    }

    /// The columns, read-only.
    pub fn columns(&self) -> &Columns {
        &self.cols
    }

    /// Back to raw columns (to edit and re-validate).
    pub fn into_columns(self) -> Columns {
        self.cols
    }

    pub fn len(&self) -> usize {
        self.cols.t_s.len()
    }

    /// Always false for a validated track (it has at least 2 samples); here for clippy's
    /// `len_without_is_empty` and for symmetry with slices.
    pub fn is_empty(&self) -> bool {
        self.cols.t_s.is_empty()
    }

    pub fn t_s(&self) -> &[f64] {
        &self.cols.t_s
    }

    /// First and last timestamp.
    pub fn span(&self) -> (f64, f64) {
        (self.cols.t_s[0], self.cols.t_s[self.cols.t_s.len() - 1])
    }

    /// Whether the track covers `[start_s, end_s]` to within `tolerance_s` at each end. Why an
    /// error and not a bool: a clip annotated from a track that stops half-way would get
    /// "no brake" for a half it never saw, so callers are meant to refuse with `?`.
    pub fn covers(&self, start_s: f64, end_s: f64, tolerance_s: f64) -> Result<(), TrackError> {
        let (a, b) = self.span();
        let ok = start_s.is_finite()
            && end_s.is_finite()
            && tolerance_s.is_finite()
            && tolerance_s >= 0.0
            && start_s <= end_s
            && a <= start_s + tolerance_s
            && b >= end_s - tolerance_s;
        if ok {
            Ok(())
        } else {
            Err(TrackError::DoesNotCover {
                start_s,
                end_s,
                track_start_s: a,
                track_end_s: b,
                tolerance_s,
            })
        }
    }

    /// [`Track::covers`] for a clip of `duration_s` whose time starts at 0.
    pub fn covers_duration(&self, duration_s: f64, tolerance_s: f64) -> Result<(), TrackError> {
        self.covers(0.0, duration_s, tolerance_s)
    }

    /// The header names of the columns present, in [`COLUMNS`] order.
    pub fn present_columns(&self) -> Vec<&'static str> {
        let mut out = vec!["t_s"];
        for (name, col) in self.cols.numeric() {
            if col.is_some() {
                out.push(name);
            }
        }
        if self.cols.turn_signal.is_some() {
            out.push("turn_signal");
        }
        out
    }

    /// CSV with a header of the present columns; missing samples as empty cells. Numbers use
    /// Rust's shortest round-trip form, so `Track::parse(to_csv())` gives back this track.
    pub fn to_csv(&self) -> String {
        let names = self.present_columns();
        let mut out = names.join(",");
        out.push('\n');
        for i in 0..self.len() {
            for (k, name) in names.iter().enumerate() {
                if k > 0 {
                    out.push(',');
                }
                match *name {
                    "t_s" => {
                        let _ = write!(out, "{}", self.cols.t_s[i]);
                    }
                    "turn_signal" => {
                        if let Some(s) = self.cols.turn_signal.as_ref().and_then(|c| c[i]) {
                            out.push_str(s.as_str());
                        }
                    }
                    other => {
                        let col = self.numeric(other);
                        if let Some(v) = col.and_then(|c| c[i]) {
                            let _ = write!(out, "{v}");
                        }
                    }
                }
            }
            out.push('\n');
        }
        out
    }

    /// JSON lines, one object per sample, absent columns left out and missing samples `null`.
    pub fn to_jsonl(&self) -> String {
        let names = self.present_columns();
        let mut out = String::new();
        for i in 0..self.len() {
            let mut obj = serde_json::Map::new();
            for name in &names {
                let v = match *name {
                    "t_s" => serde_json::Value::from(self.cols.t_s[i]),
                    "turn_signal" => match self.cols.turn_signal.as_ref().and_then(|c| c[i]) {
                        Some(s) => serde_json::Value::from(s.as_str()),
                        None => serde_json::Value::Null,
                    },
                    other => match self.numeric(other).and_then(|c| c[i]) {
                        Some(v) => serde_json::Value::from(v),
                        None => serde_json::Value::Null,
                    },
                };
                obj.insert((*name).to_string(), v);
            }
            out.push_str(&serde_json::Value::Object(obj).to_string());
            out.push('\n');
        }
        out
    }

    /// A numeric column by header name (`speed_mps`, …); `None` when absent or not numeric.
    pub fn numeric(&self, name: &str) -> Option<&[Option<f64>]> {
        self.cols
            .numeric()
            .into_iter()
            .find(|(n, _)| *n == name)
            .and_then(|(_, c)| c.as_deref())
    }

    pub fn speed_mps(&self) -> Option<&[Option<f64>]> {
        self.cols.speed_mps.as_deref()
    }
    pub fn accel_mps2(&self) -> Option<&[Option<f64>]> {
        self.cols.accel_mps2.as_deref()
    }
    pub fn steering_deg(&self) -> Option<&[Option<f64>]> {
        self.cols.steering_deg.as_deref()
    }
    pub fn yaw_rate_dps(&self) -> Option<&[Option<f64>]> {
        self.cols.yaw_rate_dps.as_deref()
    }
    pub fn brake(&self) -> Option<&[Option<f64>]> {
        self.cols.brake.as_deref()
    }
    pub fn throttle(&self) -> Option<&[Option<f64>]> {
        self.cols.throttle.as_deref()
    }
    pub fn turn_signal(&self) -> Option<&[Option<TurnSignal>]> {
        self.cols.turn_signal.as_deref()
    }
}

fn length_mismatch(name: &str, got: usize, want: usize) -> TrackError {
    TrackError::Parse {
        line: got.min(want) + 1,
        column: Some(name.to_string()),
        message: format!("column `{name}` has {got} samples but t_s has {want}"),
    }
}

/// The checks shared by parsing and [`Track::from_columns`]; `line(i)` maps sample `i` to the
/// number an error reports.
fn validate(
    cols: &Columns,
    limits: &TrackLimits,
    line: impl Fn(usize) -> usize,
) -> Result<(), TrackError> {
    let n = cols.t_s.len();
    if n > limits.max_samples {
        return Err(TrackError::TooManySamples {
            line: line(limits.max_samples),
            limit: limits.max_samples,
        });
    }
    let check = |name: &str, i: usize, v: f64| -> Result<(), TrackError> {
        if !v.is_finite() {
            return Err(TrackError::NonFinite {
                line: line(i),
                column: name.to_string(),
                value: v,
            });
        }
        let (_, min, max) = RANGES
            .iter()
            .find(|(n, _, _)| *n == name)
            .copied()
            .unwrap_or((name, f64::NEG_INFINITY, f64::INFINITY));
        if v < min || v > max {
            return Err(TrackError::OutOfRange {
                line: line(i),
                column: name.to_string(),
                value: v,
                min,
                max,
            });
        }
        Ok(())
    };
    // Row by row, so the first bad line in the input is the one reported.
    for i in 0..n {
        let t = cols.t_s[i];
        check("t_s", i, t)?;
        if i > 0 && t <= cols.t_s[i - 1] {
            return Err(TrackError::NonMonotonicTime {
                line: line(i),
                t_s: t,
                previous: cols.t_s[i - 1],
            });
        }
        for (name, col) in cols.numeric() {
            if let Some(Some(v)) = col.as_ref().map(|c| c[i]) {
                check(name, i, v)?;
            }
        }
    }
    if n < 2 {
        return Err(TrackError::Empty { samples: n });
    }
    Ok(())
}

fn parse_number(cell: &str, line: usize, column: &str) -> Result<f64, TrackError> {
    cell.parse::<f64>().map_err(|_| TrackError::Parse {
        line,
        column: Some(column.to_string()),
        message: format!("`{column}`: `{cell}` is not a number"),
    })
}

/// Splits one CSV record: comma-separated, cells trimmed, `"…"` quoting with `""` for a quote
/// (no line breaks inside quotes: no column here holds text that needs them).
fn split_csv(line_text: &str, line: usize) -> Result<Vec<String>, TrackError> {
    let mut cells = Vec::new();
    let mut cur = String::new();
    let mut chars = line_text.chars().peekable();
    let mut in_quotes = false;
    let mut was_quoted = false;
    while let Some(c) = chars.next() {
        if in_quotes {
            if c == '"' {
                if chars.peek() == Some(&'"') {
                    cur.push('"');
                    chars.next();
                } else {
                    in_quotes = false;
                }
            } else {
                cur.push(c);
            }
        } else if c == '"' && cur.trim().is_empty() && !was_quoted {
            cur.clear();
            in_quotes = true;
            was_quoted = true;
        } else if c == ',' {
            cells.push(std::mem::take(&mut cur).trim().to_string());
            was_quoted = false;
        } else {
            cur.push(c);
        }
    }
    if in_quotes {
        return Err(TrackError::Parse {
            line,
            column: None,
            message: "unterminated quoted cell".to_string(),
        });
    }
    cells.push(cur.trim().to_string());
    Ok(cells)
}

/// Column slots while parsing: index into [`COLUMNS`].
fn column_index(name: &str) -> Option<usize> {
    COLUMNS.iter().position(|c| *c == name)
}

/// Starts every column seen in the input as present and empty.
fn open_columns(seen: &[usize]) -> Columns {
    let mut cols = Columns::default();
    for &k in seen {
        match COLUMNS[k] {
            "t_s" => {}
            "turn_signal" => cols.turn_signal = Some(Vec::new()),
            name => {
                if let Some(c) = cols.numeric_mut(name) {
                    *c = Some(Vec::new());
                }
            }
        }
    }
    cols
}

fn too_many(n: usize, limits: &TrackLimits, line: usize) -> Result<(), TrackError> {
    if n >= limits.max_samples {
        Err(TrackError::TooManySamples {
            line,
            limit: limits.max_samples,
        })
    } else {
        Ok(())
    }
}

fn parse_csv(text: &str, limits: &TrackLimits) -> Result<(Columns, Vec<usize>), TrackError> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim_end_matches('\r')))
        .filter(|(_, l)| !l.trim().is_empty());
    let Some((hline, header)) = lines.next() else {
        return Err(TrackError::Empty { samples: 0 });
    };
    let names = split_csv(header, hline)?;
    let mut slots = Vec::with_capacity(names.len());
    for name in &names {
        let Some(k) = column_index(name) else {
            return Err(TrackError::UnknownColumn {
                line: hline,
                column: name.clone(),
            });
        };
        if slots.contains(&k) {
            return Err(TrackError::Parse {
                line: hline,
                column: Some(name.clone()),
                message: format!("column `{name}` appears twice in the header"),
            });
        }
        slots.push(k);
    }
    if !slots.contains(&0) {
        return Err(TrackError::MissingColumn {
            line: hline,
            column: "t_s".to_string(),
        });
    }
    let mut cols = open_columns(&slots);
    let mut line_of = Vec::new();
    for (line, record) in lines {
        too_many(cols.t_s.len(), limits, line)?;
        let cells = split_csv(record, line)?;
        if cells.len() != slots.len() {
            return Err(TrackError::Parse {
                line,
                column: None,
                message: format!(
                    "{} cells where the header names {} columns",
                    cells.len(),
                    slots.len()
                ),
            });
        }
        for (cell, &k) in cells.iter().zip(&slots) {
            let name = COLUMNS[k];
            match name {
                "t_s" => {
                    if cell.is_empty() {
                        return Err(TrackError::Parse {
                            line,
                            column: Some("t_s".to_string()),
                            message: "`t_s` is required in every row".to_string(),
                        });
                    }
                    cols.t_s.push(parse_number(cell, line, name)?);
                }
                "turn_signal" => {
                    let v = if cell.is_empty() {
                        None
                    } else {
                        Some(TurnSignal::parse(cell).ok_or_else(|| bad_signal(cell, line))?)
                    };
                    if let Some(c) = cols.turn_signal.as_mut() {
                        c.push(v);
                    }
                }
                _ => {
                    let v = if cell.is_empty() {
                        None
                    } else {
                        Some(parse_number(cell, line, name)?)
                    };
                    if let Some(Some(c)) = cols.numeric_mut(name) {
                        c.push(v);
                    }
                }
            }
        }
        line_of.push(line);
    }
    Ok((cols, line_of))
}

fn bad_signal(cell: &str, line: usize) -> TrackError {
    TrackError::Parse {
        line,
        column: Some("turn_signal".to_string()),
        message: format!("`turn_signal`: `{cell}` is not one of left, right, none"),
    }
}

fn parse_jsonl(text: &str, limits: &TrackLimits) -> Result<(Columns, Vec<usize>), TrackError> {
    // Rows as parsed cells first: which columns the track has is the union over all lines.
    type Row = (usize, [Option<Cell>; 8]);
    #[derive(Clone)]
    enum Cell {
        Num(f64),
        Signal(TurnSignal),
    }
    let mut rows: Vec<Row> = Vec::new();
    let mut seen = [false; 8];
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let raw = raw.trim();
        if raw.is_empty() {
            continue;
        }
        too_many(rows.len(), limits, line)?;
        let obj: serde_json::Map<String, serde_json::Value> =
            serde_json::from_str(raw).map_err(|e| TrackError::Parse {
                line,
                column: None,
                message: format!("not a JSON object: {e}"),
            })?;
        let mut cells: [Option<Cell>; 8] = Default::default();
        for (key, value) in &obj {
            let Some(k) = column_index(key) else {
                return Err(TrackError::UnknownColumn {
                    line,
                    column: key.clone(),
                });
            };
            seen[k] = true;
            cells[k] = match (key.as_str(), value) {
                (_, serde_json::Value::Null) => None,
                ("turn_signal", serde_json::Value::String(s)) if s.trim().is_empty() => None,
                ("turn_signal", serde_json::Value::String(s)) => Some(Cell::Signal(
                    TurnSignal::parse(s).ok_or_else(|| bad_signal(s, line))?,
                )),
                ("turn_signal", other) => {
                    return Err(TrackError::Parse {
                        line,
                        column: Some(key.clone()),
                        message: format!("`turn_signal` must be a string or null, not {other}"),
                    })
                }
                (_, serde_json::Value::Number(n)) => {
                    Some(Cell::Num(n.as_f64().ok_or_else(|| TrackError::Parse {
                        line,
                        column: Some(key.clone()),
                        message: format!("`{key}`: {n} is not representable as a float"),
                    })?))
                }
                (_, other) => {
                    return Err(TrackError::Parse {
                        line,
                        column: Some(key.clone()),
                        message: format!("`{key}` must be a number or null, not {other}"),
                    })
                }
            };
        }
        if cells[0].is_none() {
            return Err(TrackError::Parse {
                line,
                column: Some("t_s".to_string()),
                message: "`t_s` is required (a number) in every line".to_string(),
            });
        }
        rows.push((line, cells));
    }
    let slots: Vec<usize> = (0..8).filter(|&k| seen[k]).collect();
    let mut cols = open_columns(&slots);
    let mut line_of = Vec::with_capacity(rows.len());
    for (line, cells) in rows {
        for &k in &slots {
            let name = COLUMNS[k];
            match (name, &cells[k]) {
                ("t_s", Some(Cell::Num(v))) => cols.t_s.push(*v),
                ("turn_signal", c) => {
                    let v = match c {
                        Some(Cell::Signal(s)) => Some(*s),
                        _ => None,
                    };
                    if let Some(col) = cols.turn_signal.as_mut() {
                        col.push(v);
                    }
                }
                (_, c) => {
                    let v = match c {
                        Some(Cell::Num(v)) => Some(*v),
                        _ => None,
                    };
                    if let Some(Some(col)) = cols.numeric_mut(name) {
                        col.push(v);
                    }
                }
            }
        }
        line_of.push(line);
    }
    Ok((cols, line_of))
}

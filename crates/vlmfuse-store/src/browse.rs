//! Reads for the operator page (`/ui`): pages of recent rounds, one round with its feedback and
//! thumbnails, and the latest events a start seeds the page's aggregates from. Every read is a
//! bounded range over a primary key or an index, so it costs the same at any store size.

use super::*;
use crate::db::Row;

/// A frame thumbnail kept with a round (JPEG), for the operator page.
#[derive(Debug, Clone, PartialEq)]
pub struct Thumbnail {
    /// Position of the frame among the clip's sampled frames.
    pub index: u32,
    /// Its time in the clip, seconds.
    pub t_s: f64,
    pub jpeg: Vec<u8>,
}

/// A stored round as the operator page lists it.
#[derive(Debug, Clone)]
pub struct RoundRow {
    pub seq: u64,
    pub round_id: String,
    pub created_ms: i64,
    pub round: Round,
    pub inference: Inference,
    pub request: serde_json::Value,
    /// Whether any feedback was given for it.
    pub labelled: bool,
}

/// A feedback event with what its round was served with (seeding the page after a start).
#[derive(Debug, Clone)]
pub struct LabelledRow {
    pub feedback: StoredFeedback,
    pub round_id: String,
    pub round: Round,
    /// Posteriors the round was served with.
    pub q: Vec<f64>,
}

/// A [`RoundRow`]'s columns, then the statement's own `FROM` and `WHERE` (a macro so that each
/// statement stays one static string, which the PostgreSQL side prepares once).
macro_rules! round_rows {
    ($rest:literal) => {
        concat!(
            "SELECT r.seq, r.round_id, r.created_ms, r.context, r.present, r.reports, \
             d.inference, d.request, EXISTS (SELECT 1 FROM feedback f WHERE f.seq = r.seq) \
             FROM rounds r JOIN round_detail d ON d.seq = r.seq ",
            $rest
        )
    };
}

fn round_row(row: &Row) -> Result<RoundRow, StoreError> {
    Ok(RoundRow {
        seq: row.u64(0)?,
        round_id: row.string(1)?,
        created_ms: row.i64(2)?,
        round: round_from(row, 3)?,
        inference: serde_json::from_str(row.str(6)?)?,
        request: serde_json::from_str(row.str(7)?)?,
        labelled: row.bool(8)?,
    })
}

impl Store {
    /// Up to `limit` rounds before `before` (all when `None`), newest first.
    pub fn recent_rounds(
        &self,
        before: Option<u64>,
        limit: usize,
    ) -> Result<Vec<RoundRow>, StoreError> {
        let before = before.map_or(i64::MAX, |b| b.min(i64::MAX as u64) as i64);
        self.db
            .query(
                round_rows!("WHERE r.seq < ?1 ORDER BY r.seq DESC LIMIT ?2"),
                &[P::I(before), P::I(limit as i64)],
            )?
            .iter()
            .map(round_row)
            .collect()
    }

    /// One round as the page shows it.
    pub fn round_row(&self, seq: u64) -> Result<Option<RoundRow>, StoreError> {
        self.db
            .query_opt(round_rows!("WHERE r.seq = ?1"), &[P::I(seq as i64)])?
            .map(|r| round_row(&r))
            .transpose()
    }

    /// The thumbnails kept with a round, without their bytes: (index, time).
    pub fn thumbnail_index(&self, seq: u64) -> Result<Vec<(u32, f64)>, StoreError> {
        self.db
            .query(
                "SELECT idx, t_s FROM thumbnails WHERE seq = ?1 ORDER BY idx",
                &[P::I(seq as i64)],
            )?
            .iter()
            .map(|r| Ok((r.i64(0)? as u32, r.f64(1)?)))
            .collect()
    }

    /// One thumbnail's JPEG.
    pub fn thumbnail(&self, seq: u64, index: u32) -> Result<Option<Vec<u8>>, StoreError> {
        self.db
            .query_opt(
                "SELECT jpeg FROM thumbnails WHERE seq = ?1 AND idx = ?2",
                &[P::I(seq as i64), P::I(index as i64)],
            )?
            .map(|r| r.blob(0).map(<[u8]>::to_vec))
            .transpose()
    }

    /// The reputations after every `stride`-th feedback event (labelled order 0, stride, ...)
    /// and after the last one: the reputation chart's points, oldest first, as
    /// (events applied, round id, reputations). One pass over the feedback table's key.
    pub fn reputation_points(
        &self,
        stride: u64,
    ) -> Result<Vec<(u64, String, Vec<f64>)>, StoreError> {
        let stride = stride.max(1) as i64;
        let rows = self.db.query(
            "SELECT f.labelled_order, f.seq, f.outcome FROM feedback f
             WHERE f.labelled_order % ?1 = 0
                OR f.labelled_order = (SELECT MAX(labelled_order) FROM feedback)
             ORDER BY f.labelled_order",
            &[P::I(stride)],
        )?;
        let mut out = Vec::with_capacity(rows.len());
        for row in rows {
            let outcome: FeedbackOutcome = serde_json::from_str(row.str(2)?)?;
            out.push((row.u64(0)? + 1, round_id(row.u64(1)?), outcome.w_after));
        }
        Ok(out)
    }

    /// The latest `limit` feedback events, oldest first, each with its round (without its
    /// context, which the page does not need).
    pub fn recent_labelled(&self, limit: usize) -> Result<Vec<LabelledRow>, StoreError> {
        let rows = self.db.query(
            "SELECT f.seq, f.labelled_order, f.truth, f.outcome, f.rounds_before, f.source,
                    r.round_id, r.present, r.reports, r.q
             FROM feedback f JOIN rounds r ON r.seq = f.seq
             ORDER BY f.labelled_order DESC LIMIT ?1",
            &[P::I(limit as i64)],
        )?;
        let mut out = Vec::with_capacity(rows.len());
        for row in rows {
            let seq = row.u64(0)?;
            out.push(LabelledRow {
                feedback: feedback_from(&row, seq, 1)?,
                round_id: row.string(6)?,
                round: Round {
                    context: Vec::new(),
                    present: row.blob(7)?.iter().map(|&b| b != 0).collect(),
                    reports: row.blob(8)?.to_vec(),
                },
                q: blob_to_f64s(row.blob(9)?)?,
            });
        }
        out.reverse();
        Ok(out)
    }
}

/// The thumbnails of the rounds from `first_seq`, inside `tx`.
pub(crate) fn write_thumbnails(
    tx: &Db,
    first_seq: u64,
    rounds: &[NewRound],
) -> Result<(), StoreError> {
    for (i, r) in rounds.iter().enumerate() {
        for t in &r.thumbnails {
            tx.exec(
                "INSERT INTO thumbnails (seq, idx, t_s, jpeg) VALUES (?1, ?2, ?3, ?4)",
                &[
                    P::I((first_seq + i as u64) as i64),
                    P::I(t.index as i64),
                    P::F(t.t_s),
                    P::B(&t.jpeg),
                ],
            )?;
        }
    }
    Ok(())
}

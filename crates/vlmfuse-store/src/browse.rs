//! Reads for the operator page (`/ui`): pages of recent rounds, one round with its feedback and
//! thumbnails, and the latest events a start seeds the page's aggregates from. Every read is a
//! bounded range over a primary key or an index, so it costs the same at any store size.

use super::*;

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

const ROW_COLUMNS: &str = "r.seq, r.round_id, r.created_ms, r.context, r.present, r.reports, \
     d.inference, d.request, EXISTS (SELECT 1 FROM feedback f WHERE f.seq = r.seq)";

fn round_row(row: &rusqlite::Row<'_>) -> Result<RoundRow, StoreError> {
    let seq = row.get::<_, i64>(0)? as u64;
    Ok(RoundRow {
        seq,
        round_id: row.get(1)?,
        created_ms: row.get(2)?,
        round: round_from(row, 3)?,
        inference: serde_json::from_str(row.get_ref(6)?.as_str()?)?,
        request: serde_json::from_str(row.get_ref(7)?.as_str()?)?,
        labelled: row.get(8)?,
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
        let mut st = self.conn.prepare_cached(&format!(
            "SELECT {ROW_COLUMNS} FROM rounds r JOIN round_detail d ON d.seq = r.seq
             WHERE r.seq < ?1 ORDER BY r.seq DESC LIMIT ?2"
        ))?;
        let mut rows = st.query(params![before, limit as i64])?;
        let mut out = Vec::new();
        while let Some(row) = rows.next()? {
            out.push(round_row(row)?);
        }
        Ok(out)
    }

    /// One round as the page shows it.
    pub fn round_row(&self, seq: u64) -> Result<Option<RoundRow>, StoreError> {
        let mut st = self.conn.prepare_cached(&format!(
            "SELECT {ROW_COLUMNS} FROM rounds r JOIN round_detail d ON d.seq = r.seq
             WHERE r.seq = ?1"
        ))?;
        let mut rows = st.query([seq as i64])?;
        match rows.next()? {
            Some(row) => Ok(Some(round_row(row)?)),
            None => Ok(None),
        }
    }

    /// The thumbnails kept with a round, without their bytes: (index, time).
    pub fn thumbnail_index(&self, seq: u64) -> Result<Vec<(u32, f64)>, StoreError> {
        let mut st = self
            .conn
            .prepare_cached("SELECT idx, t_s FROM thumbnails WHERE seq = ?1 ORDER BY idx")?;
        let rows = st.query_map([seq as i64], |r| {
            Ok((r.get::<_, i64>(0)? as u32, r.get(1)?))
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    /// One thumbnail's JPEG.
    pub fn thumbnail(&self, seq: u64, index: u32) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self
            .conn
            .query_row(
                "SELECT jpeg FROM thumbnails WHERE seq = ?1 AND idx = ?2",
                params![seq as i64, index as i64],
                |r| r.get(0),
            )
            .optional()?)
    }

    /// The reputations after every `stride`-th feedback event (labelled order 0, stride, ...)
    /// and after the last one: the reputation chart's points, oldest first, as
    /// (events applied, round id, reputations). One pass over the feedback table's key.
    pub fn reputation_points(
        &self,
        stride: u64,
    ) -> Result<Vec<(u64, String, Vec<f64>)>, StoreError> {
        let stride = stride.max(1) as i64;
        let mut st = self.conn.prepare_cached(
            "SELECT f.labelled_order, f.seq, f.outcome FROM feedback f
             WHERE f.labelled_order % ?1 = 0
                OR f.labelled_order = (SELECT MAX(labelled_order) FROM feedback)
             ORDER BY f.labelled_order",
        )?;
        let mut rows = st.query([stride])?;
        let mut out = Vec::new();
        while let Some(row) = rows.next()? {
            let order = row.get::<_, i64>(0)? as u64;
            let seq = row.get::<_, i64>(1)? as u64;
            let outcome: FeedbackOutcome = serde_json::from_str(row.get_ref(2)?.as_str()?)?;
            out.push((order + 1, round_id(seq), outcome.w_after));
        }
        Ok(out)
    }

    /// The latest `limit` feedback events, oldest first, each with its round (without its
    /// context, which the page does not need).
    pub fn recent_labelled(&self, limit: usize) -> Result<Vec<LabelledRow>, StoreError> {
        let mut st = self.conn.prepare_cached(
            "SELECT f.seq, f.labelled_order, f.truth, f.outcome, f.rounds_before, f.source,
                    r.round_id, r.present, r.reports, r.q
             FROM feedback f JOIN rounds r ON r.seq = f.seq
             ORDER BY f.labelled_order DESC LIMIT ?1",
        )?;
        let mut rows = st.query([limit as i64])?;
        let mut out = Vec::new();
        while let Some(row) = rows.next()? {
            let seq = row.get::<_, i64>(0)? as u64;
            out.push(LabelledRow {
                feedback: feedback_from(row, seq, 1)?,
                round_id: row.get(6)?,
                round: Round {
                    context: Vec::new(),
                    present: row.get_ref(7)?.as_blob()?.iter().map(|&b| b != 0).collect(),
                    reports: row.get_ref(8)?.as_blob()?.to_vec(),
                },
                q: blob_to_f64s(row.get_ref(9)?.as_blob()?)?,
            });
        }
        out.reverse();
        Ok(out)
    }
}

/// The thumbnails of the rounds from `first_seq`, inside `tx`.
pub(crate) fn write_thumbnails(
    tx: &rusqlite::Transaction<'_>,
    first_seq: u64,
    rounds: &[NewRound],
) -> Result<(), StoreError> {
    if rounds.iter().all(|r| r.thumbnails.is_empty()) {
        return Ok(());
    }
    let mut ins =
        tx.prepare_cached("INSERT INTO thumbnails (seq, idx, t_s, jpeg) VALUES (?1, ?2, ?3, ?4)")?;
    for (i, r) in rounds.iter().enumerate() {
        for t in &r.thumbnails {
            ins.execute(params![
                (first_seq + i as u64) as i64,
                t.index as i64,
                t.t_s,
                &t.jpeg
            ])?;
        }
    }
    Ok(())
}

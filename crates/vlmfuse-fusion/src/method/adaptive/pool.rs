//! The `adaptive` method's pool: every observed round, labelled or not, with its soft truth and
//! its own list of nearest neighbours among all the others.
//!
//! A round's soft truth (its E-step posterior) depends on the reliabilities at its own context,
//! which come from its neighbours. Keeping each entry's neighbour list current (a new round is
//! inserted into the lists of the entries it is near, found in the same pass over the bank that
//! inference makes anyway) makes re-estimating one entry cost `O(K n L)` instead of a scan of the
//! pool, which is what keeps the per-round EM work bounded and a full EM pass linear in the pool.
//!
//! Neighbours are ranked by their kernel weight `max(0, cos)^tau * 2^(-|age| / h)` (the age in
//! labelled rounds between the two entries), then by cosine, then older round first. Without
//! decay that is the paper method's order exactly (cosine, then older first); with it, a recent round that is
//! a little less similar beats an old one, so decay does not empty the neighbourhood of weight.

use super::ann::{Ivf, Plan};
use super::rows::Rows;
use crate::bank::Bank;
use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, OnceLock};

/// A neighbour: position, cosine, and the ranking weight it has for the entry (or query) whose
/// list it is in.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Nb {
    pub pos: u32,
    pub sim: f64,
    pub key: f64,
}

/// What a pass over the pool found for a round about to join it.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Scan {
    /// Pool size at scan time.
    pub pool_len: usize,
    /// The pool's eviction count at scan time: positions from an earlier epoch are stale.
    pub epoch: u64,
    /// The round's own neighbours, best first.
    pub top: Vec<Nb>,
    /// Entries that may take the round as a neighbour, with exact cosines, in pool order.
    pub rev: Vec<(usize, f64)>,
    /// The approximate index's cell of the round's context, when the scan went through it
    /// (the cells never move, so the insertion need not compare it with the centres again).
    pub cell: Option<u32>,
    /// The bank's f32 first pass over the whole pool, when the exact scan made one: the
    /// switch's `paper` candidate ranks its labelled window from it instead of a pass of its own.
    pub first_pass: Option<std::sync::Arc<FirstPass>>,
}

/// What a scan learnt of every pool entry's cosine to a round's context, in pool order.
#[derive(Debug, Clone, PartialEq)]
pub enum FirstPass {
    /// Exact cosines ([`crate::bank::Bank::sim`]), where the pool is small enough to score
    /// every entry exactly.
    Exact(Vec<f64>),
    /// Approximate cosines and the rigorous bounds on their errors
    /// ([`crate::bank::Bank::approx_with_bounds`]).
    Approx {
        approx: Vec<f32>,
        bound: Vec<f64>,
        /// The exact cosines the scan computed (its survivors), NaN elsewhere: the `paper`
        /// candidate's search of the same round reuses them instead of scoring them again.
        known: Vec<f64>,
    },
}

impl FirstPass {
    /// Entries covered.
    pub fn len(&self) -> usize {
        match self {
            FirstPass::Exact(s) => s.len(),
            FirstPass::Approx { approx, .. } => approx.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Pool {
    /// Contexts, presence and reports (its truths are unused: soft truths live here).
    pub(crate) bank: Bank,
    n: usize,
    l: usize,
    /// Neighbours kept per entry: `max(K, K_prior)`.
    kmax: usize,
    tau: f64,
    half_life: f64,
    /// Per entry, in one block of cache lines ([`Rows`]): its `L` soft truths (the truth itself
    /// once labelled), whether it is labelled or partly labelled, and a copy of its presence
    /// flags and reports: what a neighbour's weighted sums read.
    rows: Rows,
    /// `L` soft truths per entry under the whole-pool Dawid–Skene (`super::ds`), which ignores
    /// context: the known labels' truths, else that model's E-step posterior. Renumbered with
    /// the rows on eviction.
    gsoft: Vec<f64>,
    /// The engine's labelled-round count when the entry was observed (its age clock).
    clock: Vec<u64>,
    /// Per entry: up to `kmax` neighbours, best first.
    nb: Vec<Vec<Nb>>,
    #[serde(with = "crate::sorted_map")]
    by_seq: HashMap<u64, usize>,
    /// Positions of the unlabelled entries, ascending: what EM visits.
    unlabelled: Vec<u32>,
    /// Per entry: the cosine of the worst neighbour it keeps when its list is full, else
    /// `-inf`. A flat copy of `nb[j].last().sim`, so that a scan tests every entry without
    /// chasing one pointer per entry (the lists are separate allocations). Used only without
    /// decay, where the ranking weight is a monotone function of the cosine.
    worst_sim: Vec<f64>,
    /// Evictions so far ([`Pool::evict`]); a scan is valid only in its own epoch.
    epoch: u64,
    /// The approximate index ([`super::ann`]), built when the pool first holds `ann_min`
    /// entries (0: never) with `ann_cells` cells; a query probes `ann_probe` cells and scores
    /// `ann_ef` candidates exactly.
    ann: Option<Ivf>,
    ann_min: usize,
    ann_cells: usize,
    ann_probe: usize,
    ann_ef: usize,
    /// The index's candidates for a context, found ahead of the round's scan while the index
    /// was out of the pool ([`Pool::take_ann`]); used by the scan only for that very context
    /// and index state. Not state: never saved, and a scan with it is the scan without it.
    #[serde(skip)]
    ahead: Option<Ahead>,
}

/// [`Ivf::candidates`] for one context (its f32 copy), found for the index as it stood at
/// `pool_len` entries in eviction epoch `epoch` (every change to the index changes one of
/// the two).
#[derive(Debug, Clone)]
pub struct Ahead {
    x: Vec<f32>,
    pool_len: usize,
    epoch: u64,
    /// The candidates in ascending order, and `x`'s cell.
    found: (Vec<usize>, u32),
    /// The candidates' exact cosines to `xd` (the f64 context), when the job had the bank's
    /// rows ([`Bank::take_rows`]): what [`Pool::ann_scan`] would compute, so it uses them for
    /// the very same context only.
    exact: Option<(Vec<f64>, Vec<f64>)>,
}

/// A search for [`Ahead`] candidates, from [`Pool::ahead_job`].
#[derive(Debug, Clone, Copy)]
pub struct AheadJob {
    probe: usize,
    ef: usize,
    pool_len: usize,
    epoch: u64,
    dim: usize,
}

impl AheadJob {
    /// The index's candidates for context `x` (see [`Pool::ann_scan`]) on the index taken out
    /// by [`Pool::take_ann`]: the next scan of `x` uses them if the index has not changed by
    /// then. A pure function of the index and `x`, so finding them ahead changes no result.
    ///
    /// With `rows` (a compact bank's, from [`Bank::take_rows`]) it also scores the candidates
    /// exactly, as the scan would: the largest part of a scan's own work at scale is reading
    /// those scattered rows, and here it runs beside the EM chunk too.
    #[cfg(test)]
    pub fn run(self, ivf: &Ivf, rows: Option<&[f32]>, x: &[f64]) -> Ahead {
        let xf: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        let (cand, cell) = ivf.candidates(&xf, self.probe, self.ef);
        self.finish(cand, cell, rows, x, &xf)
    }

    /// The candidates `cand` of `x` (cell `cell`) in ascending order, with their exact scores
    /// when the rows came along.
    fn finish(
        self,
        mut cand: Vec<usize>,
        cell: u32,
        rows: Option<&[f32]>,
        x: &[f64],
        xf: &[f32],
    ) -> Ahead {
        cand.sort_unstable();
        let exact = rows
            .filter(|r| self.dim > 0 && r.len() == self.pool_len * self.dim)
            .map(|r| {
                let mut sims = Vec::with_capacity(cand.len());
                crate::bank::sims_in(r, self.dim, x, &cand, &mut sims);
                (x.to_vec(), sims)
            });
        Ahead {
            x: xf.to_vec(),
            pool_len: self.pool_len,
            epoch: self.epoch,
            found: (cand, cell),
            exact,
        }
    }
}

/// A probed cell's approximate similarities, with their positions, once scored.
type Slot = Mutex<Vec<(f32, usize)>>;

/// An [`AheadJob`] under way on the helper thread, which the caller's thread can join once its
/// own half is done ([`Search::help`]): at a million rounds the search of a 200,000-entry pool
/// is the longer of the two halves. The probed cells are handed out one at a time; each cell is
/// scored by the same function on whichever thread takes it, and the candidates are selected
/// from the cells in the plan's order, so the result is [`AheadJob::run`]'s, bit for bit
/// (tested), whoever scored what.
pub struct Search {
    job: AheadJob,
    ivf: Ivf,
    rows: Option<Vec<f32>>,
    x: Vec<f64>,
    xf: Vec<f32>,
    /// The plan, and a slot per probed cell for its scores.
    plan: OnceLock<(Plan, Vec<Slot>)>,
    next: AtomicUsize,
    done: AtomicUsize,
}

impl Search {
    /// The search of `x` on the index and rows taken out of the pool ([`Pool::take_ann`],
    /// [`Bank::take_rows`]); nothing runs yet.
    pub fn new(job: AheadJob, ivf: Ivf, rows: Option<Vec<f32>>, x: &[f64]) -> Self {
        Self {
            job,
            ivf,
            rows,
            x: x.to_vec(),
            xf: x.iter().map(|&v| v as f32).collect(),
            plan: OnceLock::new(),
            next: AtomicUsize::new(0),
            done: AtomicUsize::new(0),
        }
    }

    /// The plan (made on first call) and its cells' slots.
    fn planned(&self) -> &(Plan, Vec<Slot>) {
        self.plan.get_or_init(|| {
            let plan = self.ivf.plan(&self.xf, self.job.probe, self.job.ef);
            let parts = plan.cells.iter().map(|_| Mutex::default()).collect();
            (plan, parts)
        })
    }

    fn claim(&self, plan: &Plan, parts: &[Slot]) {
        loop {
            let i = self.next.fetch_add(1, Ordering::AcqRel);
            if i >= plan.cells.len() {
                return;
            }
            let scored = self.ivf.score_cell(plan, i);
            *parts[i].lock().unwrap_or_else(|e| e.into_inner()) = scored;
            self.done.fetch_add(1, Ordering::AcqRel);
        }
    }

    /// The caller's share: scores probed cells while any are left, once the search has
    /// planned them (else it returns at once).
    pub fn help(&self) {
        if let Some((plan, parts)) = self.plan.get() {
            self.claim(plan, parts);
        }
    }

    /// The whole search (on the helper, or on the caller when the helper never started it):
    /// the plan, a share of the cells, the selection once every cell is scored, and the exact
    /// scores of the candidates.
    pub fn run(&self) -> Ahead {
        let (plan, parts) = self.planned();
        self.claim(plan, parts);
        while self.done.load(Ordering::Acquire) < plan.cells.len() {
            std::hint::spin_loop();
        }
        let scored = parts
            .iter()
            .map(|p| std::mem::take(&mut *p.lock().unwrap_or_else(|e| e.into_inner())));
        let cand = plan.select(scored);
        self.job
            .finish(cand, plan.own, self.rows.as_deref(), &self.x, &self.xf)
    }

    /// The index and rows, to be put back into the pool.
    pub fn into_parts(self) -> (Ivf, Option<Vec<f32>>) {
        (self.ivf, self.rows)
    }

    /// Copies of the index and rows, when another handle still holds the search.
    pub fn copy_parts(&self) -> (Ivf, Option<Vec<f32>>) {
        (self.ivf.clone(), self.rows.clone())
    }
}

/// `max(0, s)^tau`; the default `tau = 4` as two squarings (a `powf` per pool entry per scan
/// was a twentieth of a round; the two agree to an ulp).
#[inline]
pub fn kernel(s: f64, tau: f64) -> f64 {
    let s = s.max(0.0);
    if tau == 4.0 {
        let q = s * s;
        q * q
    } else {
        s.powf(tau)
    }
}

/// `2^(-age / h)`, exactly 1 without decay.
#[inline]
pub fn decay(age: f64, half_life: f64) -> f64 {
    if half_life > 0.0 {
        (-age / half_life).exp2()
    } else {
        1.0
    }
}

impl Pool {
    pub fn new(n: usize, l: usize, kmax: usize, tau: f64, half_life: f64) -> Self {
        Self {
            bank: Bank::new(n, l),
            n,
            l,
            kmax,
            tau,
            half_life,
            rows: Rows::new(n, l),
            gsoft: Vec::new(),
            clock: Vec::new(),
            nb: Vec::new(),
            by_seq: HashMap::new(),
            unlabelled: Vec::new(),
            worst_sim: Vec::new(),
            epoch: 0,
            ann: None,
            ann_min: 0,
            ann_cells: 0,
            ann_probe: 0,
            ann_ef: 0,
            ahead: None,
        }
    }

    /// Uses the approximate index once the pool holds `min` entries (0: never): `cells` cells,
    /// `probe` of them searched per query, `ef` candidates scored exactly. Call it on an empty
    /// pool.
    pub fn approximate(mut self, min: usize, cells: usize, probe: usize, ef: usize) -> Self {
        debug_assert_eq!(self.len(), 0);
        self.ann_min = min;
        self.ann_cells = cells;
        self.ann_probe = probe;
        self.ann_ef = ef;
        self
    }

    /// Whether scans use the approximate index, and the share of the exact scan's neighbours
    /// its scans find for these queries (clock `at`).
    pub fn recall(&self, queries: &[Vec<f64>], at: u64) -> (bool, f64) {
        let (mut hit, mut total) = (0usize, 0usize);
        for x in queries {
            let got: Vec<u32> = self.scan(x, at).top.iter().map(|n| n.pos).collect();
            let want = self.scan_exact(x, at).top;
            hit += want.iter().filter(|n| got.contains(&n.pos)).count();
            total += want.len();
        }
        (self.ann_active(), hit as f64 / total.max(1) as f64)
    }

    /// Whether scans use the approximate index.
    pub fn ann_active(&self) -> bool {
        self.ann.is_some()
    }

    /// After an insertion: the entry joins its cell, or, when the pool first reaches
    /// `ann_min`, the cells are fixed over the whole pool.
    fn ann_after_insert(&mut self, pos: usize, cell: Option<u32>) {
        if let Some(ivf) = self.ann.as_mut() {
            ivf.push(self.bank.f32_row(pos), cell);
            debug_assert_eq!(ivf.len(), self.bank.len());
        } else if self.ann_min > 0 && self.len() >= self.ann_min {
            self.ann = Some(Ivf::train(
                self.bank.f32_rows(),
                self.bank.dim(),
                self.ann_cells,
            ));
        }
    }

    /// Takes the approximate index out of the pool (`None` when it is not in use), so that
    /// [`Pool::find_ahead`] can search it on another thread while work that never reads it
    /// (EM's E-steps) goes on. Give it back with [`Pool::put_ann`] before anything else.
    pub fn take_ann(&mut self) -> Option<Ivf> {
        self.ann.take()
    }

    /// Puts back the index [`Pool::take_ann`] took, with the candidates found meanwhile.
    pub fn put_ann(&mut self, ivf: Ivf, ahead: Option<Ahead>) {
        debug_assert!(self.ann.is_none());
        self.ann = Some(ivf);
        self.ahead = ahead;
    }

    /// What [`AheadJob::run`] needs of the pool as it is now, so that the search can run on
    /// another thread without borrowing the pool.
    pub fn ahead_job(&self) -> AheadJob {
        AheadJob {
            probe: self.ann_probe,
            ef: self.ann_ef.max(self.kmax),
            pool_len: self.len(),
            epoch: self.epoch,
            dim: self.bank.dim(),
        }
    }

    /// [`Pool::scan`] through the approximate index: its `ann_ef` candidates are scored exactly
    /// and ranked as the exact scan ranks; the entries whose list the round may enter are
    /// looked for among them.
    fn ann_scan(&self, ivf: &Ivf, x: &[f64], at: u64) -> Scan {
        let len = self.len();
        let m = self.kmax.min(len);
        let xf: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        let same = |a: &[f64], b: &[f64]| {
            a.len() == b.len() && a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits())
        };
        let (cand, cell, scored) = match &self.ahead {
            Some(a)
                if a.pool_len == len
                    && a.epoch == self.epoch
                    && a.x.len() == xf.len()
                    && a.x.iter().zip(&xf).all(|(p, q)| p.to_bits() == q.to_bits()) =>
            {
                let scored = a
                    .exact
                    .as_ref()
                    .filter(|(xd, _)| same(xd, x))
                    .map(|(_, sims)| sims.clone());
                (a.found.0.clone(), a.found.1, scored)
            }
            _ => {
                let (mut cand, cell) =
                    ivf.candidates(&xf, self.ann_probe, self.ann_ef.max(self.kmax));
                cand.sort_unstable();
                (cand, cell, None)
            }
        };
        #[cfg(target_arch = "x86_64")]
        if scored.is_none() {
            for &j in &cand {
                let row = self.bank.f32_row(j).as_ptr() as *const i8;
                // SAFETY: a prefetch is a hint; the pointer is the start of a live slice.
                unsafe { std::arch::x86_64::_mm_prefetch(row, std::arch::x86_64::_MM_HINT_T0) };
            }
        }
        // What the round's inference reads of its neighbours next (soft truths, reports),
        // for every candidate: the neighbours are among them.
        self.prefetch(cand.iter().copied());
        let mut rev = Vec::new();
        // Without decay, entering a list is a cosine test against its flat copy of the worst
        // kept cosine (as in the exact scan): no pointer chase, no `powf`, per candidate; and
        // ranking by weight is ranking by cosine, so only the kept neighbours' weights are
        // computed.
        let by_sim = self.half_life <= 0.0 && self.worst_sim.len() == len;
        let sims = scored.unwrap_or_else(|| {
            let mut sims = Vec::with_capacity(cand.len());
            self.bank.sims(x, &cand, &mut sims);
            sims
        });
        let top = if by_sim {
            let mut best: Vec<(usize, f64)> = Vec::with_capacity(cand.len());
            for (&j, &sim) in cand.iter().zip(&sims) {
                if sim >= self.worst_sim[j] {
                    rev.push((j, sim));
                }
                best.push((j, sim));
            }
            self.best_by_sim(best, m, at)
        } else {
            let mut top = Vec::with_capacity(cand.len());
            for (&j, &sim) in cand.iter().zip(&sims) {
                top.push(self.nb_at(j, sim, at));
                if self.may_enter(j, sim, at) {
                    rev.push((j, sim));
                }
            }
            self.rank(&mut top, m);
            top
        };
        Scan {
            pool_len: len,
            epoch: self.epoch,
            top,
            rev,
            cell: Some(cell),
            first_pass: None,
        }
    }

    /// Keeps contexts as f32 only (see [`Bank::new_compact`]). Call it on an empty pool.
    pub fn compact(mut self, on: bool) -> Self {
        debug_assert_eq!(self.len(), 0);
        if on {
            self.bank = Bank::new_compact(self.n, self.l);
        }
        self
    }

    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// Removes the entries with `dead[pos]` true and renumbers the others, keeping their order
    /// (the bounded pool's retention). Neighbour lists lose the removed entries, so lists may be
    /// shorter than `kmax` until later rounds fill them again.
    pub fn evict(&mut self, dead: &[bool]) {
        let len = self.len();
        debug_assert_eq!(dead.len(), len);
        let mut map = vec![None; len];
        let mut next = 0u32;
        for (pos, m) in map.iter_mut().enumerate() {
            if !dead[pos] {
                *m = Some(next);
                next += 1;
            }
        }
        let keep: Vec<bool> = dead.iter().map(|d| !d).collect();
        self.bank.retain(&keep);
        self.rows.retain(&keep);
        if let Some(ivf) = self.ann.as_mut() {
            ivf.retain(&keep);
        }
        let l = self.l;
        let mut w = 0;
        for (r, &gone) in dead.iter().enumerate() {
            if gone {
                continue;
            }
            if w != r {
                self.gsoft.copy_within(r * l..(r + 1) * l, w * l);
                self.clock[w] = self.clock[r];
                self.nb.swap(w, r);
            }
            w += 1;
        }
        self.gsoft.truncate(w * l);
        self.clock.truncate(w);
        self.nb.truncate(w);
        for list in &mut self.nb {
            list.retain_mut(|e| match map[e.pos as usize] {
                Some(p) => {
                    e.pos = p;
                    true
                }
                None => false,
            });
        }
        self.by_seq.retain(|_, pos| match map[*pos] {
            Some(p) => {
                *pos = p as usize;
                true
            }
            None => false,
        });
        self.unlabelled = (0..w as u32)
            .filter(|&p| !self.rows.labelled(p as usize))
            .collect();
        if !self.worst_sim.is_empty() {
            self.worst_sim = (0..w).map(|p| self.worst_of(p)).collect();
        }
        self.epoch += 1;
    }

    pub fn len(&self) -> usize {
        self.clock.len()
    }

    pub fn position(&self, seq: u64) -> Option<usize> {
        self.by_seq.get(&seq).copied()
    }

    /// Asks the processor to start loading what [`Adaptive`](super::Adaptive)'s weighted sums
    /// read of these entries (their rows), so that the misses of a large pool overlap instead
    /// of coming one neighbour at a time. A hint only: no effect on any result.
    #[inline]
    pub fn prefetch(&self, positions: impl Iterator<Item = usize>) {
        for pos in positions {
            self.rows.prefetch(pos);
        }
    }

    /// Asks the processor to start loading entry `pos`'s neighbour list and its own soft truth
    /// and reports (what an E-step of it reads first): issued a step or two ahead of the
    /// E-steps of one event, whose entries are known in advance, so that each E-step finds its
    /// neighbours' positions in cache. A hint only.
    #[inline]
    pub fn prefetch_entry(&self, pos: usize) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            let list = self.nb[pos].as_ptr() as *const i8;
            let bytes = self.nb[pos].len() * std::mem::size_of::<Nb>();
            // SAFETY: hints only; the pointers are in (or one past) live allocations.
            unsafe {
                let mut off = 0;
                while off < bytes {
                    _mm_prefetch(list.wrapping_add(off), _MM_HINT_T0);
                    off += 64;
                }
            }
            self.prefetch(std::iter::once(pos));
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = pos;
    }

    #[inline]
    pub fn soft(&self, pos: usize) -> &[f64] {
        self.rows.soft(pos)
    }

    /// The entry's presence flags (0/1), as the bank holds them, from its row.
    #[inline]
    pub fn present_row(&self, pos: usize) -> &[u8] {
        self.rows.present(pos)
    }

    /// The entry's `n L` reports, as the bank holds them, from its row.
    #[inline]
    pub fn reports_row(&self, pos: usize) -> &[u8] {
        self.rows.reports(pos)
    }

    /// The entry's soft truths under the whole-pool Dawid–Skene.
    pub fn gsoft(&self, pos: usize) -> &[f64] {
        &self.gsoft[pos * self.l..(pos + 1) * self.l]
    }

    /// Sets the whole-pool Dawid–Skene soft truths of the entry's unknown labels to `t`; its
    /// known labels keep their truth.
    pub fn set_gsoft(&mut self, pos: usize, t: &[f64]) {
        let l = self.l;
        for (k, &tk) in t.iter().enumerate().take(l) {
            self.gsoft[pos * l + k] = if self.known(pos, k) {
                self.rows.soft(pos)[k]
            } else {
                tk
            };
        }
    }

    pub fn is_labelled(&self, pos: usize) -> bool {
        self.rows.labelled(pos)
    }

    /// Some, not all, of the entry's labels are known (partial feedback): the entry stays with
    /// the unlabelled ones for EM, which re-estimates only its unknown labels, is never evicted,
    /// and its known labels weigh as labelled ones do. Which labels are known is its bank truth
    /// (0/1 known, [`crate::UNKNOWN`] not).
    #[inline]
    pub fn is_partial(&self, pos: usize) -> bool {
        self.rows.partial(pos)
    }

    /// Whether label `k` of entry `pos` is known (labelled, or given by a partial feedback).
    #[inline]
    pub fn known(&self, pos: usize, k: usize) -> bool {
        self.rows.labelled(pos) || self.bank.truth(pos, k) <= 1
    }

    /// A (partial) feedback on entry `pos`: each label `y` knows (0 or 1) becomes known with
    /// that value, overriding an earlier one; the entry is labelled once every label is known.
    pub fn set_known(&mut self, pos: usize, y: &[u8]) {
        self.bank.merge_truth(pos, y);
        let l = self.l;
        for (k, &v) in y.iter().enumerate() {
            if v <= 1 {
                self.rows.soft_mut(pos)[k] = v as f64;
                self.gsoft[pos * l + k] = v as f64;
            }
        }
        let full: Vec<u8> = (0..l).map(|k| self.bank.truth(pos, k)).collect();
        if full.iter().all(|&v| v <= 1) {
            self.rows.set_partial(pos, false);
            self.set_label(pos, &full);
        } else {
            let partial = !self.rows.labelled(pos);
            self.rows.set_partial(pos, partial);
        }
    }

    /// Positions of the unlabelled entries, ascending.
    pub fn unlabelled(&self) -> &[u32] {
        &self.unlabelled
    }

    pub fn clock(&self, pos: usize) -> u64 {
        self.clock[pos]
    }

    pub fn neighbours(&self, pos: usize) -> &[Nb] {
        &self.nb[pos]
    }

    pub fn present(&self, pos: usize) -> Vec<bool> {
        self.rows.present(pos).iter().map(|&p| p != 0).collect()
    }

    /// The entry's reports as the bank holds them, from its row.
    pub fn reports(&self, pos: usize) -> Vec<u8> {
        self.rows.reports(pos).to_vec()
    }

    pub fn set_soft(&mut self, pos: usize, t: &[f64]) {
        self.rows.soft_mut(pos).copy_from_slice(t);
    }

    pub fn set_label(&mut self, pos: usize, y: &[u8]) {
        let l = self.l;
        for (k, &v) in y.iter().enumerate() {
            self.rows.soft_mut(pos)[k] = v as f64;
            self.gsoft[pos * l + k] = v as f64;
        }
        if !self.rows.labelled(pos) {
            if let Ok(i) = self.unlabelled.binary_search(&(pos as u32)) {
                self.unlabelled.remove(i);
            }
        }
        self.rows.set_labelled(pos, true);
    }

    /// The ranking weight of an entry observed at clock `c` with cosine `sim`, seen from clock
    /// `at`.
    #[inline]
    pub fn key(&self, sim: f64, c: u64, at: u64) -> f64 {
        let k = kernel(sim, self.tau);
        if self.half_life > 0.0 && k > 0.0 {
            k * decay((at as f64 - c as f64).abs(), self.half_life)
        } else {
            k
        }
    }

    /// Entry `j` as a neighbour, with cosine `sim`, of a round observed at clock `at`.
    #[inline]
    fn nb_at(&self, j: usize, sim: f64, at: u64) -> Nb {
        Nb {
            pos: j as u32,
            sim,
            key: self.key(sim, self.clock[j], at),
        }
    }

    /// `a` ranks before `b`: higher weight, then higher cosine, then the older round.
    #[inline]
    fn before(&self, a: &Nb, b: &Nb) -> bool {
        a.key > b.key
            || (a.key == b.key
                && (a.sim > b.sim
                    || (a.sim == b.sim
                        && self.bank.seq(a.pos as usize) < self.bank.seq(b.pos as usize))))
    }

    /// The worst neighbour an entry keeps, when its list is full (a newcomer must beat it).
    fn worst(&self, pos: usize) -> Option<&Nb> {
        let list = &self.nb[pos];
        if list.len() < self.kmax {
            None
        } else {
            list.last()
        }
    }

    /// The cosine a newcomer must reach to enter `pos`'s list: its worst neighbour's when the
    /// list is full, else `-inf`.
    fn worst_of(&self, pos: usize) -> f64 {
        self.worst(pos).map_or(f64::NEG_INFINITY, |w| w.sim)
    }

    /// Sorts neighbours best first and keeps `m` (a selection first, so that ranking a whole
    /// small pool costs O(n + m log m)).
    pub fn rank(&self, v: &mut Vec<Nb>, m: usize) {
        let cmp = |a: &Nb, b: &Nb| {
            b.key.total_cmp(&a.key).then(b.sim.total_cmp(&a.sim)).then(
                self.bank
                    .seq(a.pos as usize)
                    .cmp(&self.bank.seq(b.pos as usize)),
            )
        };
        if m == 0 {
            v.clear();
            return;
        }
        if v.len() > m {
            v.select_nth_unstable_by(m - 1, cmp);
            v.truncate(m);
        }
        v.sort_by(cmp);
    }

    /// Without decay, ranking by weight is ranking by cosine (ties to the older round): the
    /// `m` best of these `(position, cosine)` pairs by cosine, with their weights, ranked. Only
    /// the kept ones' weights are computed.
    fn best_by_sim(&self, mut best: Vec<(usize, f64)>, m: usize, at: u64) -> Vec<Nb> {
        if m == 0 {
            return Vec::new();
        }
        if best.len() > m {
            let cmp = |a: &(usize, f64), b: &(usize, f64)| {
                b.1.total_cmp(&a.1)
                    .then(self.bank.seq(a.0).cmp(&self.bank.seq(b.0)))
            };
            best.select_nth_unstable_by(m - 1, cmp);
            best.truncate(m);
        }
        let mut top: Vec<Nb> = best
            .into_iter()
            .map(|(j, s)| self.nb_at(j, s, at))
            .collect();
        self.rank(&mut top, m);
        top
    }

    /// Whether a newcomer at clock `at` with cosine `sim` to entry `j` may enter `j`'s list. A
    /// filter only: `insert` settles exact ties by age.
    fn may_enter(&self, j: usize, sim: f64, at: u64) -> bool {
        match self.worst(j) {
            None => true,
            Some(_) => self.may_enter_with(j, sim, self.key(sim, at, self.clock[j])),
        }
    }

    /// [`Pool::may_enter`] with the newcomer's weight `key` already known.
    #[inline]
    fn may_enter_with(&self, j: usize, sim: f64, key: f64) -> bool {
        match self.worst(j) {
            None => true,
            Some(w) => key > w.key || (key == w.key && sim >= w.sim),
        }
    }

    /// [`Pool::scan`] with the cosines computed elsewhere (a batched GEMM): `sims[seq]` is the
    /// round's cosine to the round numbered `seq`, for every `seq` the pool holds.
    pub fn scan_by_seq(&self, sims: &[f64], at: u64) -> Scan {
        let len = self.len();
        let m = self.kmax.min(len);
        let sim = |j: usize| sims[self.bank.seq(j) as usize];
        let mut top: Vec<Nb> = Vec::new();
        let mut rev: Vec<(usize, f64)> = Vec::new();
        if self.half_life <= 0.0 && self.worst_sim.len() == len {
            // Without decay, ranking by weight is ranking by cosine (see `scan`): the `m` best
            // cosines are selected first and only their weights computed.
            let mut best: Vec<(usize, f64)> = Vec::with_capacity(len);
            for j in 0..len {
                let s = sim(j);
                if s >= self.worst_sim[j] {
                    rev.push((j, s));
                }
                best.push((j, s));
            }
            top = self.best_by_sim(best, m, at);
        } else {
            for j in 0..len {
                let s = sim(j);
                top.push(self.nb_at(j, s, at));
                if self.may_enter(j, s, at) {
                    rev.push((j, s));
                }
            }
            self.rank(&mut top, m);
        }
        Scan {
            pool_len: len,
            epoch: self.epoch,
            top,
            rev,
            cell: None,
            first_pass: None,
        }
    }

    /// One pass over the pool for a round with context `x` (unit norm) observed at clock `at`:
    /// its `kmax` best neighbours and the entries whose list it may enter. Large pools use the
    /// bank's f32 first pass with its rigorous bound: only entries whose weight could reach the
    /// cut are scored exactly.
    pub fn scan(&self, x: &[f64], at: u64) -> Scan {
        match &self.ann {
            Some(ivf) => self.ann_scan(ivf, x, at),
            None => self.scan_exact(x, at),
        }
    }

    /// [`Pool::scan`] over every entry, whether or not the approximate index is in use.
    pub fn scan_exact(&self, x: &[f64], at: u64) -> Scan {
        let len = self.len();
        let m = self.kmax.min(len);
        let mut top: Vec<Nb> = Vec::new();
        let mut rev: Vec<(usize, f64)> = Vec::new();
        let newcomer_beats = |j: usize, sim: f64| self.may_enter(j, sim, at);
        let by_sim = self.half_life <= 0.0 && self.worst_sim.len() == len;
        let first = self.bank.approx_with_bounds(x);
        let mut exact: Option<Vec<f64>> = None;
        // Exact cosines computed so far (NaN: not yet): an entry both a reverse candidate and
        // a survivor is scored once, and the `paper` candidate reuses them (`FirstPass`).
        let mut known: Vec<f64> = if first.is_some() {
            vec![f64::NAN; len]
        } else {
            Vec::new()
        };
        let bank = &self.bank;
        let mut sim_of = |j: usize| {
            let v = known[j];
            if v.is_nan() {
                let s = bank.sim(x, j);
                known[j] = s;
                s
            } else {
                v
            }
        };
        match first.as_ref().map(|(a, b)| (a, b)) {
            Some((approx, bound)) if by_sim => {
                // Without decay the weight `max(0, s)^tau` is a non-decreasing function of the
                // cosine and ties are broken by the cosine, so ranking by weight is ranking by
                // cosine: every test below is done on cosines (no `powf` per entry) and the
                // weight is computed only for the entries scored exactly.
                let mut lo: Vec<f64> = Vec::with_capacity(len);
                for j in 0..len {
                    let a = approx[j] as f64;
                    lo.push(a - bound[j]);
                    if a + bound[j] >= self.worst_sim[j] {
                        let sim = sim_of(j);
                        if sim >= self.worst_sim[j] {
                            rev.push((j, sim));
                        }
                    }
                }
                if m > 0 {
                    let (_, &mut cut, _) = lo.select_nth_unstable_by(m - 1, |a, b| b.total_cmp(a));
                    for j in 0..len {
                        if approx[j] as f64 + bound[j] >= cut {
                            let sim = sim_of(j);
                            top.push(self.nb_at(j, sim, at));
                        }
                    }
                    self.rank(&mut top, m);
                }
            }
            None => {
                let mut all = Vec::with_capacity(len);
                for j in 0..len {
                    let sim = self.bank.sim(x, j);
                    all.push(sim);
                    let nb = self.nb_at(j, sim, at);
                    // The weight is symmetric in the two clocks: the one computed for `top`.
                    if self.may_enter_with(j, sim, nb.key) {
                        rev.push((j, sim));
                    }
                    top.push(nb);
                }
                self.rank(&mut top, m);
                exact = Some(all);
            }
            Some((approx, bound)) => {
                let mut lo: Vec<f64> = Vec::with_capacity(len);
                for j in 0..len {
                    let a = approx[j] as f64;
                    lo.push(self.key(a - bound[j], self.clock[j], at));
                    let up = a + bound[j];
                    let reach = match self.worst(j) {
                        None => true,
                        Some(w) => self.key(up, at, self.clock[j]) >= w.key,
                    };
                    if reach {
                        let sim = sim_of(j);
                        if newcomer_beats(j, sim) {
                            rev.push((j, sim));
                        }
                    }
                }
                if m > 0 {
                    let mut sel = lo.clone();
                    let (_, &mut cut, _) = sel.select_nth_unstable_by(m - 1, |a, b| b.total_cmp(a));
                    for j in 0..len {
                        let up = self.key(approx[j] as f64 + bound[j], self.clock[j], at);
                        if up >= cut {
                            let sim = sim_of(j);
                            top.push(self.nb_at(j, sim, at));
                        }
                    }
                    self.rank(&mut top, m);
                }
            }
        }
        Scan {
            pool_len: len,
            epoch: self.epoch,
            top,
            rev,
            cell: None,
            first_pass: match (exact, first) {
                (Some(e), _) => Some(std::sync::Arc::new(FirstPass::Exact(e))),
                (None, Some((approx, bound))) => Some(std::sync::Arc::new(FirstPass::Approx {
                    approx,
                    bound,
                    known,
                })),
                (None, None) => None,
            },
        }
    }

    /// Completes a scan made when the pool was shorter with the entries that joined since.
    pub fn extend_scan(&self, x: &[f64], at: u64, scan: &Scan) -> Scan {
        let len = self.len();
        let mut top = scan.top.clone();
        let mut rev = scan.rev.clone();
        for j in scan.pool_len..len {
            let sim = self.bank.sim(x, j);
            top.push(self.nb_at(j, sim, at));
            rev.push((j, sim));
        }
        self.rank(&mut top, self.kmax);
        Scan {
            pool_len: len,
            epoch: self.epoch,
            top,
            rev,
            cell: scan.cell,
            // Covers the first `scan.pool_len` entries only: users check the pool's length.
            first_pass: None,
        }
    }

    /// Appends a round observed at clock `clock`, with its neighbours from [`Pool::scan`].
    #[allow(clippy::too_many_arguments)]
    pub fn insert(
        &mut self,
        seq: u64,
        context: &[f64],
        present: &[bool],
        reports: &[u8],
        soft: &[f64],
        labelled: bool,
        clock: u64,
        scan: &Scan,
    ) -> usize {
        let pos = self.len();
        // The bank's truths say which labels are known (see `partial`).
        let truth: Vec<u8> = if labelled {
            soft.iter().map(|&t| (t > 0.5) as u8).collect()
        } else {
            vec![crate::UNKNOWN; self.l]
        };
        self.bank.push(seq, context, present, reports, &truth);
        self.rows.push(soft, labelled, false, present, reports);
        self.gsoft.extend_from_slice(soft);
        if !labelled {
            self.unlabelled.push(pos as u32);
        }
        self.clock.push(clock);
        self.by_seq.insert(seq, pos);
        self.nb
            .push(scan.top.iter().take(self.kmax).copied().collect());
        let track = self.worst_sim.len() == pos;
        if track {
            let w = self.worst_of(pos);
            self.worst_sim.push(w);
        }
        let me = pos as u32;
        for &(j, sim) in &scan.rev {
            let entry = Nb {
                pos: me,
                sim,
                key: self.key(sim, clock, self.clock[j]),
            };
            if let Some(w) = self.worst(j) {
                if !self.before(&entry, w) {
                    continue;
                }
            }
            let at = self.nb[j]
                .iter()
                .position(|e| self.before(&entry, e))
                .unwrap_or(self.nb[j].len());
            let list = &mut self.nb[j];
            list.insert(at, entry);
            if list.len() > self.kmax {
                list.pop();
            }
            if track {
                self.worst_sim[j] = self.worst_of(j);
            }
        }
        self.ann_after_insert(pos, scan.cell);
        pos
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bank::dot_f32;

    /// The cosine the pool computes between a newcomer `x` and an older entry `c`: against the
    /// entry's f32 copy (its bank is compact).
    fn sim_to_entry(x: &[f64], c: &[f64]) -> f64 {
        let c32: Vec<f32> = c.iter().map(|&v| v as f32).collect();
        dot_f32(x, &c32)
    }

    fn unit(v: &[f64]) -> Vec<f64> {
        let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        v.iter().map(|x| x / n).collect()
    }

    fn rnd(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 11) as f64 / (1u64 << 53) as f64) - 0.5
    }

    /// Builds a pool of `count` rounds and checks every entry's list against a brute-force
    /// ranking over all other entries.
    fn check(count: usize, dim: usize, half_life: f64, quantise: bool) {
        let mut state = 17u64;
        let mut pool = Pool::new(1, 1, 6, 4.0, half_life).compact(true);
        let mut ctx = Vec::new();
        let mut clocks = Vec::new();
        for s in 0..count as u64 {
            let v: Vec<f64> = (0..dim)
                .map(|_| {
                    let r = rnd(&mut state);
                    if quantise {
                        (r * 4.0).round() + 0.01
                    } else {
                        r
                    }
                })
                .collect();
            let x = unit(&v);
            let clock = s / 3;
            let scan = pool.scan(&x, clock);
            pool.insert(s, &x, &[true], &[0], &[0.0], false, clock, &scan);
            ctx.push(x);
            clocks.push(clock);
        }
        for j in 0..ctx.len() {
            let mut all: Vec<Nb> = (0..ctx.len())
                .filter(|&i| i != j)
                .map(|i| {
                    // Computed once, when the newer of the two joined.
                    let sim = if i > j {
                        sim_to_entry(&ctx[i], &ctx[j])
                    } else {
                        sim_to_entry(&ctx[j], &ctx[i])
                    };
                    Nb {
                        pos: i as u32,
                        sim,
                        key: pool.key(sim, clocks[i], clocks[j]),
                    }
                })
                .collect();
            pool.rank(&mut all, 6);
            let want: Vec<u32> = all.iter().map(|e| e.pos).collect();
            let got: Vec<u32> = pool.neighbours(j).iter().map(|e| e.pos).collect();
            assert_eq!(got, want, "entry {j}");
        }
    }

    /// Scanning with the cosines given (by `seq`) builds the same pool as scanning.
    fn check_given_cosines(count: usize, half_life: f64) {
        let mut state = 5u64;
        let mut scanned = Pool::new(2, 1, 6, 4.0, half_life).compact(true);
        let mut given = Pool::new(2, 1, 6, 4.0, half_life).compact(true);
        let mut ctx: Vec<Vec<f64>> = Vec::new();
        for s in 0..count as u64 {
            let x = unit(&(0..5).map(|_| rnd(&mut state)).collect::<Vec<_>>());
            let clock = s / 4;
            // Sequence numbers with gaps, as in a store where some rounds never joined.
            let seq = 3 * s + 1;
            let mut sims = vec![f64::NAN; seq as usize];
            for (j, c) in ctx.iter().enumerate() {
                sims[3 * j + 1] = sim_to_entry(&x, c);
            }
            let a = scanned.scan(&x, clock);
            let b = given.scan_by_seq(&sims, clock);
            assert_eq!(a.top, b.top, "round {s}");
            scanned.insert(seq, &x, &[true, true], &[0, 1], &[0.5], false, clock, &a);
            given.insert(seq, &x, &[true, true], &[0, 1], &[0.5], false, clock, &b);
            ctx.push(x);
        }
        for j in 0..count {
            assert_eq!(scanned.neighbours(j), given.neighbours(j), "entry {j}");
        }
    }

    /// A search whose cells two threads share ([`Search`]) finds what the helper alone finds
    /// ([`AheadJob::run`]): the same candidates and the same exact cosines, bit for bit, however
    /// the cells were split (a thread joins as soon as the plan exists, so the split varies).
    #[test]
    fn a_search_shared_by_two_threads_finds_what_one_finds() {
        let mut state = 29u64;
        let (mut pool, centres) = scene_pool(&mut state, 48, 30, 5000, 20, (2000, 64, 16, 100));
        let job = pool.ahead_job();
        let ivf = pool.take_ann().expect("the index is in use");
        let rows = pool.bank.take_rows();
        let mut done = Vec::new();
        for q in 0..40 {
            let x = clustered(&mut state, &centres, 0.5);
            let want = job.run(&ivf, rows.as_deref(), &x);
            let search = Search::new(job, ivf.clone(), rows.clone(), &x);
            // Before the plan exists, helping does nothing.
            search.help();
            assert_eq!(search.next.load(Ordering::Relaxed), 0);
            let got = std::thread::scope(|sc| {
                if q % 3 == 1 {
                    // This thread holds a cell while the other runs the search: the search
                    // must wait for it.
                    let (plan, parts) = search.planned();
                    let i = search.next.fetch_add(1, Ordering::AcqRel);
                    let helper = sc.spawn(|| search.run());
                    std::thread::sleep(std::time::Duration::from_millis(20));
                    assert!(!helper.is_finished(), "the search left a held cell behind");
                    *parts[i].lock().unwrap() = search.ivf.score_cell(plan, i);
                    search.done.fetch_add(1, Ordering::AcqRel);
                    return helper.join().unwrap();
                }
                let helper = sc.spawn(|| search.run());
                if q % 3 == 0 {
                    while search.plan.get().is_none() {
                        std::hint::spin_loop();
                    }
                    search.help();
                }
                helper.join().unwrap()
            });
            done.push(search.done.load(Ordering::Relaxed));
            assert_eq!(got.found, want.found, "query {q}");
            let bits = |a: &Ahead| {
                let (x, s) = a.exact.as_ref().expect("scored exactly");
                (
                    x.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    s.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                )
            };
            assert_eq!(bits(&got), bits(&want), "query {q}");
            assert_eq!(got.x, want.x);
            assert_eq!((got.pool_len, got.epoch), (want.pool_len, want.epoch));
            let (back, back_rows) = search.into_parts();
            assert_eq!(back.len(), ivf.len());
            assert_eq!(back_rows.map(|r| r.len()), rows.as_ref().map(|r| r.len()));
        }
        assert!(
            done.iter().all(|&d| d == 16),
            "every probed cell scored once"
        );
    }

    /// A compact pool of `count` scene-like contexts of `dim` around `scenes` centres (entry
    /// `s` observed at clock `s`), keeping `kmax` neighbours, with the index `(min, cells,
    /// probe, ef)`; and the centres, for queries like them.
    fn scene_pool(
        state: &mut u64,
        dim: usize,
        scenes: usize,
        count: usize,
        kmax: usize,
        (min, cells, probe, ef): (usize, usize, usize, usize),
    ) -> (Pool, Vec<Vec<f64>>) {
        let centres: Vec<Vec<f64>> = (0..scenes)
            .map(|_| (0..dim).map(|_| rnd(state)).collect())
            .collect();
        let mut pool = Pool::new(1, 1, kmax, 4.0, 0.0)
            .compact(true)
            .approximate(min, cells, probe, ef);
        for s in 0..count as u64 {
            let x = clustered(state, &centres, 0.5);
            let scan = pool.scan(&x, s);
            pool.insert(s, &x, &[true], &[0], &[0.0], false, s, &scan);
        }
        (pool, centres)
    }

    /// Contexts around a few centres, as scenes are.
    fn clustered(state: &mut u64, centres: &[Vec<f64>], spread: f64) -> Vec<f64> {
        let c = &centres[((rnd(state) + 0.5) * centres.len() as f64) as usize % centres.len()];
        unit(
            &c.iter()
                .map(|v| v + spread * rnd(state))
                .collect::<Vec<_>>(),
        )
    }

    /// Candidates scored ahead on the rows taken out of the bank give the scan the fresh scan
    /// gives, for the context they were scored for; for one that differs only below f32's
    /// precision (the same candidates) the cosines are computed afresh, not taken.
    #[test]
    fn cosines_scored_ahead_serve_only_their_own_context() {
        let mut state = 5u64;
        let (pool, centres) = scene_pool(&mut state, 24, 12, 900, 10, (300, 16, 4, 40));
        assert!(pool.ann_active());
        let x = clustered(&mut state, &centres, 0.5);
        // The same context moved by 2^-35 of one coordinate: its f32 copy, and so its
        // candidates, are those of `x`; its exact cosines are not.
        let mut near = x.clone();
        near[0] *= 1.0 + 2f64.powi(-35);
        assert_eq!(near[0] as f32, x[0] as f32);
        let fresh = |q: &[f64]| pool.clone().scan(q, 7);
        let (want_x, want_near) = (fresh(&x), fresh(&near));
        let differ = want_x
            .top
            .iter()
            .zip(&want_near.top)
            .any(|(a, b)| a.sim.to_bits() != b.sim.to_bits());
        assert!(differ, "the two contexts must differ in some cosine");
        let bits = |s: &Scan| {
            s.top
                .iter()
                .map(|n| (n.pos, n.sim.to_bits(), n.key.to_bits()))
                .chain(s.rev.iter().map(|&(j, sim)| (j as u32, sim.to_bits(), 0)))
                .collect::<Vec<_>>()
        };
        for (q, want) in [(&x, &want_x), (&near, &want_near)] {
            let mut ahead = pool.clone();
            let job = ahead.ahead_job();
            let ivf = ahead.take_ann().unwrap();
            let rows = ahead.bank.take_rows();
            assert!(rows.is_some(), "a compact bank lends its rows");
            let found = job.run(&ivf, rows.as_deref(), &x);
            assert!(found.exact.is_some());
            ahead.bank.put_rows(rows);
            ahead.put_ann(ivf, Some(found));
            assert_eq!(bits(&ahead.scan(q, 7)), bits(want));
        }
    }

    #[test]
    fn the_approximate_index_recalls_the_exact_neighbours() {
        let (dim, count) = (48, 6000);
        let mut state = 23u64;
        let centres: Vec<Vec<f64>> = (0..40)
            .map(|_| (0..dim).map(|_| rnd(&mut state)).collect())
            .collect();
        let mut pool = Pool::new(1, 1, 20, 4.0, 0.0)
            .compact(true)
            .approximate(2000, 64, 8, 100);
        for s in 0..count as u64 {
            let x = clustered(&mut state, &centres, 0.5);
            assert_eq!(pool.ann_active(), s >= 2000, "round {s}");
            let scan = pool.scan(&x, s / 10);
            pool.insert(s, &x, &[true], &[0], &[0.0], false, s / 10, &scan);
        }
        // Query, then evict a third (the index renumbers with the pool) and query again.
        let mut reverse = (0, 0);
        for round in 0..2 {
            let (mut hit, mut total) = (0, 0);
            for _ in 0..200 {
                let x = clustered(&mut state, &centres, 0.5);
                let approx = pool.scan(&x, 600);
                let exact = pool.scan_exact(&x, 600);
                let got: Vec<u32> = approx.top.iter().map(|n| n.pos).collect();
                hit += exact.top.iter().filter(|n| got.contains(&n.pos)).count();
                total += exact.top.len();
                if round == 0 {
                    let rev: Vec<usize> = approx.rev.iter().map(|r| r.0).collect();
                    reverse.0 += exact.rev.iter().filter(|r| rev.contains(&r.0)).count();
                    reverse.1 += exact.rev.len();
                }
                // Candidates are scored exactly: every cosine found is the exact one.
                for n in &approx.top {
                    assert_eq!(n.sim, pool.bank.sim(&x, n.pos as usize));
                }
            }
            let recall = hit as f64 / total as f64;
            assert!(
                recall >= 0.95,
                "recall@20 {recall:.3} (after eviction: {round})"
            );
            let dead: Vec<bool> = (0..pool.len()).map(|p| p % 3 == 1).collect();
            pool.evict(&dead);
        }
        let rev_recall = reverse.0 as f64 / reverse.1 as f64;
        assert!(reverse.1 > 200, "{reverse:?}");
        assert!(
            rev_recall >= 0.9,
            "reverse-neighbour recall {rev_recall:.3}"
        );
    }

    #[test]
    fn given_cosines_scan_as_the_pool_does() {
        check_given_cosines(300, 0.0);
        check_given_cosines(300, 25.0);
    }

    #[test]
    fn neighbour_lists_equal_a_brute_force_ranking_with_ties() {
        // Quantised coordinates: many exact ties, which must go to the older round (`dot` sums in
        // one fixed order, so it is exactly symmetric and ties stay ties).
        check(400, 3, 0.0, true);
    }

    #[test]
    fn neighbour_lists_with_decay_and_the_f32_first_pass() {
        check(2600, 8, 0.0, false);
        check(2600, 8, 40.0, false);
    }
}

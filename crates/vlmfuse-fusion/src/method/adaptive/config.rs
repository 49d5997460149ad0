//! The `adaptive` method's parameters (docs/METHOD.md names each symbol). Every switch has an
//! "off" value, and with all of them off (see [`AdaptiveConfig::paper_equivalent`]) the method
//! is the paper method's exactly, which the invariant tests check.

use serde::{Deserialize, Serialize};

/// How reputations weight the reporters' log-likelihood ratios.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WeightNorm {
    /// `w_i / max_j w_j`: weights proportional to reputation, as docs/PAPER-METHOD.md has them, but scaled so
    /// that the most trusted reporter counts its LLR in full. With uniform reputations every
    /// weight is one, the sum of LLRs is the Dawid–Skene posterior (what the E-step needs to be
    /// a probability, not one shrunken by `1/n`), and no reporter ever counts more than its
    /// reliabilities say its report is worth.
    #[default]
    MaxOne,
    /// `min(1, n * w_i / full_weight_at)`: a reporter whose reputation is at least
    /// `full_weight_at` times the average counts its LLR in full
    /// (the Dawid–Skene posterior, which the E-step needs to be a probability and not a
    /// shrunken one), one below it proportionally less.
    Capped,
    /// `n * w_i`: weights average one.
    MeanOne,
    /// `w_i` as docs/PAPER-METHOD.md has it (weights sum to one: posteriors shrink by about `1/n`).
    SumOne,
}

/// Where the guardrail's error correlations `rho` come from.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Guardrail {
    /// Error co-occurrence over every labelled round in the pool (decayed like every pool sum),
    /// shrunk toward 0 by the evidence behind it: `rho * M / (M + corr_shrink)` with `M` the
    /// (decayed) number of rounds in the table. With the paper method's +0.5 smoothing alone, ten rounds on
    /// which two reporters never err read as rho = 0.45, which silences agreement exactly when
    /// little is known. Unlabelled rounds do not count: errors measured against the engine's own
    /// guesses make agreement look like correlated error and feed back into the guesses.
    #[default]
    Pool,
    /// The paper method's window of the last `corr_window` labelled rounds.
    Window,
}

/// How reputations follow the credits.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Reputation {
    /// A softmax of each reporter's recent (discounted) mean credit, its slope cut to a twentieth
    /// beyond `credit_cap`: `w_i ~ exp(beta * (min(m_i, cap) + max(0, m_i - cap) / 20))`. Old
    /// credit is forgotten (a reporter that turns bad loses its influence within a few memory
    /// half-lives, one that recovers wins it back); beyond the cap a good reporter gains slowly,
    /// so it does not crowd out the others that also help, and the better of two always ranks
    /// higher.
    #[default]
    Discounted,
    /// The paper method's `w_i <- w_i exp(eta phi_i) / Z` (on scaled credits when `credit_half_life > 0`).
    Multiplicative,
}

/// What an unlabelled round's soft truth is.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SoftTruth {
    /// The Dawid–Skene posterior proper: `sigmoid(logit(pi) + sum_i lambda_ik)` with every
    /// weight one and no guardrail, as classical EM has it. Reputations and the guardrail shape
    /// the prediction; fed back into the soft truths they would shrink the evidence a little at
    /// every pass, and EM would drift toward reporters that look like coins.
    #[default]
    Ds,
    /// The fused posterior before calibration, `sigmoid(z)`.
    Raw,
    /// The calibrated posterior.
    Calibrated,
}

/// Which predictor decides a round.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Serve {
    /// The candidate (whole-pool Dawid–Skene, the context-aware model, majority vote) with the
    /// lowest recent loss on the labelled rounds, scored before each label is learned
    /// (docs/METHOD.md §3; `switch_*`). Dawid–Skene until labels say otherwise.
    #[default]
    Switch,
    /// Majority vote until the model's decisions over every labelled round have fewer Hamming
    /// errors than the vote's and a micro-F1 no lower; then the model (the rule before the
    /// switch: it served the vote for most rounds on data it was not tuned on).
    VoteFallback,
    /// The model always.
    Model,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AdaptiveConfig {
    /// What multiplies each LLR: `w_i / max w` (max-one), `min(1, n w_i / full_weight_at)`
    /// (capped), `n w_i` (mean-one) or the paper method's `w_i` (sum-one).
    pub weights: WeightNorm,
    /// Under `capped`: the reputation, as a multiple of the average `1/n`, from which a
    /// reporter's LLR counts in full.
    pub full_weight_at: f64,

    /// Cold prior of the reliabilities, the "better than chance" belief that holds before any
    /// evidence: `theta+ ~ mu+`, `theta- ~ mu-` with `prior_strength` pseudo-observations each.
    /// `mu+ > mu-` makes an unknown reporter a (weak) voter, never a coin.
    pub prior_tpr: f64,
    pub prior_fpr: f64,
    pub prior_strength: f64,
    /// Shrink each local (kernel-weighted) reliability toward the reporter's whole-pool one
    /// instead of toward the cold prior: rare labels and sparse neighbourhoods borrow strength
    /// from every round the reporter was seen in.
    pub hierarchical: bool,
    /// Pseudo-observations the whole-pool reliability carries into a local estimate.
    pub local_strength: f64,
    /// Cold prior of the whole-pool label frequency `pi-bar`: Beta with mean 1/2 and this mass.
    pub prior_pi_strength: f64,
    /// Pseudo-observations the whole-pool frequency carries into the contextual prior `pi`.
    pub local_pi_strength: f64,

    /// Weight of an unlabelled round's soft truth relative to a labelled round's truth in every
    /// kernel sum. 0 switches semi-supervision off (unlabelled rounds then teach nothing).
    pub unlabelled_weight: f64,
    /// Whether an unlabelled round's soft truth is the calibrated or the raw posterior.
    pub soft_truth: SoftTruth,
    /// Source of the guardrail's error correlations.
    pub guardrail: Guardrail,
    /// Rounds of evidence at which the `pool` guardrail's correlation counts half.
    pub corr_shrink: f64,
    /// Labelled rounds at which unlabelled rounds count half of `unlabelled_weight`: the
    /// effective weight is `unlabelled_weight * N / (N + unlabelled_ramp)` with `N` labelled
    /// rounds so far. Soft truths are the engine's own guesses; before labels anchor them,
    /// learning from them is Dawid–Skene on agreement alone, which correlated reporters
    /// mislead (on the hard file it loses to a plain vote). 0 gives them full weight at once.
    pub unlabelled_ramp: f64,
    /// Most unlabelled neighbours whose soft truth is refreshed when a round gets its label.
    pub refresh_max: usize,
    /// Unlabelled rounds re-estimated (E-step) per observed or labelled round, cycling through
    /// the pool: EM that runs a little with every event, so its result depends on the events
    /// alone and never on timing (replays are exact). 5: as many benchmark-suite points as 10
    /// (docs/METHOD.md §6) for about a fifth less time per unlabelled round.
    pub em_chunk: usize,
    /// Most unlabelled rounds the pool keeps (0: all). Labelled rounds are always kept; past
    /// the cap (plus a slack of a sixteenth of it) the oldest unlabelled rounds leave, so that
    /// memory and the per-round scan stay bounded however long the service runs.
    pub pool_max: usize,
    /// Keep the pool's contexts as f32 only (a third of the memory; cosines move by about
    /// 1e-7, no metric of the benchmark suite moves). Off, they are kept in f64 as the paper
    /// method's bank keeps them, which `paper_equivalent` needs to match it to 1e-9.
    pub compact_contexts: bool,
    /// Pool size from which a round's neighbours are found through an approximate index (an
    /// inverted file of k-means cells over 8-bit contexts, candidates re-scored exactly;
    /// docs/METHOD.md §6) instead of the exact scan, whose cost grows with the pool. 0: always
    /// exact. The cells are fixed when the pool first reaches this size.
    pub ann_min: usize,
    /// Cells of the index.
    pub ann_cells: usize,
    /// Cells searched per query (nearest centres first). More: better recall, slower.
    pub ann_probe: usize,
    /// Candidates (best 8-bit cosines among the searched cells) scored exactly per query; at
    /// least `max(k, k_prior)`.
    pub ann_ef: usize,

    /// Half-life of evidence, in labelled rounds: a round `a` labelled rounds older counts
    /// `2^(-a / half_life)`. 0 switches decay off.
    pub half_life: f64,
    /// Decay the contextual prior `pi` too. Off by default: drift is in the reporters; how often
    /// a label is true in a scene is about the world, and halving that evidence every half-life
    /// throws away the context (on the hard file it costs more than the drift gains).
    pub decay_prior: bool,
    /// Rank neighbours by decayed kernel weight instead of by cosine (recent rounds first).
    pub decay_ranking: bool,
    /// Reputation learning rate (the paper method's `eta`, for this method), per unit of typical credit
    /// when `credit_half_life > 0`.
    pub eta: f64,
    /// Half-life, in labelled rounds, of the running mean of `|phi|` that credits are divided by
    /// before the reputation update, so that `eta` and `fixed_share` mean the same on data whose
    /// credits are a tenth or ten times those of another. 0 uses raw credits (as docs/PAPER-METHOD.md does).
    pub credit_half_life: f64,
    /// How reputations follow the credits.
    pub reputation: Reputation,
    /// `discounted`: half-life, in the reporter's labelled rounds, of its mean credit.
    pub credit_memory: f64,
    /// `discounted`: rounds of zero credit every reporter's mean starts with, so that a few
    /// lucky or unlucky rounds do not swing the reputations: `m_i = S_i / (D_i + prior)`.
    pub credit_prior_rounds: f64,
    /// `discounted`: inverse temperature `beta` of the softmax over mean scaled credits.
    pub reputation_beta: f64,
    /// `discounted`: the mean scaled credit beyond which it counts a twentieth as much, so no
    /// reporter crowds out the others while the ranking stays that of the credits.
    pub credit_cap: f64,
    /// Fixed-share mixing after each reputation update: `w <- (1 - alpha) w + alpha / n`, so no
    /// reporter's weight ever falls below `alpha / n` and a recovered reporter can win back.
    pub fixed_share: f64,

    /// Per-label Platt scaling of the fused logit.
    pub calibration: bool,
    /// Labelled rounds whose inference-time logits the calibration is fitted on.
    pub calib_window: usize,
    /// Precision of each label's Platt parameters around the pooled fit (pseudo-observations).
    pub calib_label_prior: f64,
    /// Precision of the pooled Platt parameters around the identity (slope 1, intercept 0).
    pub calib_pooled_prior: f64,
    /// Newton steps per refit (warm-started from the previous fit).
    pub calib_newton_steps: usize,
    /// Smallest Platt slope: calibration may flatten a logit, never invert it.
    pub calib_min_slope: f64,

    /// Which predictor decides a round: `switch` (the default), `vote-fallback` or `model`.
    pub serve: Serve,
    /// `switch`: the factor each candidate's loss so far is multiplied by before a labelled
    /// round adds to it (1: every round counts forever; 0.99: about the last 100).
    pub switch_discount: f64,
    /// `switch`: what a missed label costs, against 1 for a false alarm.
    pub switch_fn_cost: f64,
    /// `switch`: how much lower another candidate's loss must be than the serving one's before
    /// it serves (hysteresis: no flipping on ties and noise).
    pub switch_margin: f64,
    /// `switch`: labelled rounds scored before the serving candidate may change at all. Until
    /// then Dawid–Skene, which needs no label, serves: a loss gap over a handful of rounds is
    /// mostly noise (the model, too, keeps its initial threshold until `threshold_min_rounds`).
    pub switch_min_rounds: u64,
    /// `switch`: before `switch_min_rounds`, the switch may change (at `switch_margin`) once two
    /// reporters' errors on the labelled rounds are more dependent than this: the count-weighted
    /// mean over labels of the phi coefficient of their error co-occurrence (0: never). Reporters
    /// that err together look reliable to Dawid–Skene, which serves until then, because they
    /// agree. 0.7 lies above every set of the suite's dev instances (real classifiers reach 0.62)
    /// and below two reporters that share their errors (0.76 after 10 labels).
    pub switch_dependence: f64,
    /// `switch`: the model/paper mean's loss is compared at `1 - switch_mean_edge` times its
    /// value. Its two halves are learners whose scores lag behind them (each labelled round
    /// is scored before it is learnt) and whose errors are partly independent, so at equal past
    /// loss the mean tends to be the better choice from here on (docs/METHOD.md §3).
    pub switch_mean_edge: f64,
    /// `switch`: the `paper` candidate (PAPER-METHOD.md's rule over the pool's labelled
    /// entries) searches only the latest `paper_window` labelled rounds for its neighbours, so
    /// that its cost per round is bounded at any scale (and it forgets what drift made stale).
    /// 0 leaves the candidate out.
    pub paper_window: usize,
    /// The whole-pool Dawid–Skene's pseudo-observations pulling each label's reliabilities
    /// toward the reporter's pooled over labels (docs/METHOD.md §3).
    pub ds_label_strength: f64,
    /// Decision threshold until `threshold_min_rounds` rounds are labelled: the grid point just
    /// above 1/2, so a label is on when its posterior is MORE than one half (the Bayes rule for
    /// Hamming loss on calibrated posteriors, and majority vote's "more than half" on a tie).
    pub threshold_initial: f64,
    pub threshold_min_rounds: usize,
    /// Labelled rounds at which the fitted threshold has moved half-way from
    /// `threshold_initial` to the grid point that maximises mean Jaccard:
    /// `t = t0 + (t_fit - t0) N / (N + threshold_shrink)`, snapped to the grid. A Jaccard
    /// optimum over a few dozen rounds is noisy and sits low (Jaccard rewards recall); with few
    /// labels the Bayes rule for calibrated posteriors is the better bet. 0 uses `t_fit`.
    pub threshold_shrink: f64,
}

impl Default for AdaptiveConfig {
    fn default() -> Self {
        Self {
            weights: WeightNorm::MaxOne,
            full_weight_at: 0.5,
            prior_tpr: 0.7,
            prior_fpr: 0.3,
            prior_strength: 4.0,
            hierarchical: true,
            local_strength: 4.0,
            prior_pi_strength: 2.0,
            local_pi_strength: 2.0,
            unlabelled_weight: 1.0,
            soft_truth: SoftTruth::Ds,
            guardrail: Guardrail::Pool,
            corr_shrink: 50.0,
            unlabelled_ramp: 20.0,
            refresh_max: 50,
            em_chunk: 5,
            pool_max: 100_000,
            compact_contexts: true,
            ann_min: 20_000,
            ann_cells: 512,
            ann_probe: 12,
            ann_ef: 100,
            half_life: 0.0,
            eta: 0.03,
            decay_prior: false,
            decay_ranking: false,
            credit_half_life: 200.0,
            reputation: Reputation::Discounted,
            credit_memory: 30.0,
            credit_prior_rounds: 10.0,
            reputation_beta: 8.0,
            credit_cap: 0.25,
            fixed_share: 0.03,
            calibration: true,
            calib_window: 500,
            calib_label_prior: 20.0,
            calib_pooled_prior: 5.0,
            calib_newton_steps: 1,
            calib_min_slope: 0.05,
            serve: Serve::Switch,
            switch_discount: 0.99,
            switch_dependence: 0.7,
            switch_fn_cost: 1.5,
            switch_margin: 3.0,
            switch_min_rounds: 20,
            switch_mean_edge: 0.03,
            paper_window: 2_000,
            ds_label_strength: 30.0,
            threshold_initial: 0.505,
            threshold_min_rounds: 20,
            threshold_shrink: 100.0,
        }
    }
}

impl AdaptiveConfig {
    /// Every extension off: with every round labelled the method is the paper method's, bit for bit
    /// (reputation rate `eta` and the threshold rule taken from the paper's settings).
    pub fn paper_equivalent(eta: f64, threshold_initial: f64, threshold_min_rounds: usize) -> Self {
        Self {
            weights: WeightNorm::SumOne,
            prior_tpr: 0.5,
            prior_fpr: 0.5,
            prior_strength: 2.0,
            hierarchical: false,
            unlabelled_weight: 0.0,
            guardrail: Guardrail::Window,
            half_life: 0.0,
            eta,
            credit_half_life: 0.0,
            reputation: Reputation::Multiplicative,
            fixed_share: 0.0,
            calibration: false,
            threshold_initial,
            threshold_min_rounds,
            threshold_shrink: 0.0,
            serve: Serve::Model,
            compact_contexts: false,
            ann_min: 0,
            ..Self::default()
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        let prob = |v: f64, name: &str| {
            if v > 0.0 && v < 1.0 {
                Ok(())
            } else {
                Err(format!("{name} must lie in (0, 1), got {v}"))
            }
        };
        let pos = |v: f64, name: &str| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(format!("{name} must be a positive finite number, got {v}"))
            }
        };
        let nonneg = |v: f64, name: &str| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(format!("{name} must be finite and >= 0, got {v}"))
            }
        };
        pos(self.full_weight_at, "full_weight_at")?;
        prob(self.prior_tpr, "prior_tpr")?;
        prob(self.prior_fpr, "prior_fpr")?;
        pos(self.prior_strength, "prior_strength")?;
        pos(self.local_strength, "local_strength")?;
        pos(self.prior_pi_strength, "prior_pi_strength")?;
        pos(self.local_pi_strength, "local_pi_strength")?;
        nonneg(self.unlabelled_weight, "unlabelled_weight")?;
        if self.unlabelled_weight > 1.0 {
            return Err(format!(
                "unlabelled_weight must not exceed 1 (a guess never counts more than a label), \
                 got {}",
                self.unlabelled_weight
            ));
        }
        nonneg(self.half_life, "half_life")?;
        nonneg(self.corr_shrink, "corr_shrink")?;
        nonneg(self.unlabelled_ramp, "unlabelled_ramp")?;
        nonneg(self.eta, "eta")?;
        nonneg(self.credit_half_life, "credit_half_life")?;
        nonneg(self.credit_memory, "credit_memory")?;
        nonneg(self.credit_prior_rounds, "credit_prior_rounds")?;
        nonneg(self.reputation_beta, "reputation_beta")?;
        nonneg(self.credit_cap, "credit_cap")?;
        if !(0.0..1.0).contains(&self.fixed_share) {
            return Err(format!(
                "fixed_share must lie in [0, 1), got {}",
                self.fixed_share
            ));
        }
        if self.calib_window == 0 {
            return Err("calib_window must be at least 1".into());
        }
        pos(self.calib_label_prior, "calib_label_prior")?;
        pos(self.calib_pooled_prior, "calib_pooled_prior")?;
        if !(self.calib_min_slope.is_finite() && self.calib_min_slope >= 0.0) {
            return Err("calib_min_slope must be finite and >= 0".into());
        }
        nonneg(self.threshold_shrink, "threshold_shrink")?;
        if !(self.switch_discount > 0.0 && self.switch_discount <= 1.0) {
            return Err(format!(
                "switch_discount must lie in (0, 1], got {}",
                self.switch_discount
            ));
        }
        nonneg(self.switch_fn_cost, "switch_fn_cost")?;
        nonneg(self.switch_margin, "switch_margin")?;
        if !(0.0..=1.0).contains(&self.switch_dependence) {
            return Err(format!(
                "switch_dependence must lie in [0, 1], got {}",
                self.switch_dependence
            ));
        }
        if !(0.0..1.0).contains(&self.switch_mean_edge) {
            return Err(format!(
                "switch_mean_edge must lie in [0, 1), got {}",
                self.switch_mean_edge
            ));
        }
        nonneg(self.ds_label_strength, "ds_label_strength")?;
        if self.serve != Serve::Model {
            // sigmoid(ln(tpr / fpr)): the vote's posterior with a one-vote majority.
            let top = self.prior_tpr / (self.prior_tpr + self.prior_fpr);
            if !(self.threshold_initial > 0.5 && self.threshold_initial < top) {
                return Err(format!(
                    "serving the vote, threshold_initial must lie in (0.5, {top:.3}) so that the \
                     vote's posterior decides as majority vote does, got {}",
                    self.threshold_initial
                ));
            }
            if self.prior_tpr <= self.prior_fpr {
                return Err("serving the vote, prior_tpr must exceed prior_fpr".into());
            }
        }
        if !(0.0..=1.0).contains(&self.threshold_initial) {
            return Err("threshold_initial must lie in [0, 1]".into());
        }
        if self.ann_min > 0 && (self.ann_cells == 0 || self.ann_probe == 0 || self.ann_ef == 0) {
            return Err(
                "with ann_min > 0, ann_cells, ann_probe and ann_ef must be at least 1".into(),
            );
        }
        Ok(())
    }
}

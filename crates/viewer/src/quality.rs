//! The quality ladder: while the camera moves, the viewer renders at the most expensive rung whose
//! predicted time fits the frame budget; once it stops, it climbs the ladder one rung per UI frame
//! up to the chosen settings. Rungs change only the resolution and sample counts, which reach the
//! kernel through its `Params` uniform and the dispatch size, so no rung builds a new pipeline.
//! Two rungs at the chosen resolution with fewer samples are drawn only from the baked field
//! (`crate::bake`): there a lookup is cheap enough that a drag keeps the full resolution with some
//! of the samples instead of dropping to a quarter of the rays.

use lp3d_renderer::RenderSettings;

/// One step of the ladder: a resolution and sample counts derived from the chosen settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rung {
    pub resolution: u32,
    pub depth_resolution: u32,
    pub depth_resolution_importance: u32,
}

impl Rung {
    pub fn of(settings: &RenderSettings) -> Rung {
        Rung {
            resolution: settings.resolution,
            depth_resolution: settings.depth_resolution,
            depth_resolution_importance: settings.depth_resolution_importance,
        }
    }

    /// Rays times samples per ray: a frame's time scales about with this.
    pub fn cost(&self) -> f64 {
        let rays = self.resolution as f64 * self.resolution as f64;
        rays * (self.depth_resolution + self.depth_resolution_importance) as f64
    }

    /// The rung with the resolution divided by `res_div` and the samples by `samples_div`.
    fn divided(&self, (res_div, samples_div): (u32, u32)) -> Rung {
        self.scaled(res_div, (1, samples_div), (1, samples_div))
    }

    /// The rung with the resolution divided by `res_div`, the coarse samples scaled by `coarse`
    /// and the fine ones by `fine` (numerator, denominator; rounded down), within the renderer's
    /// limits (an importance pass needs 4 coarse samples and 2 fine ones; 8 rays per side at least).
    fn scaled(&self, res_div: u32, coarse: (u32, u32), fine: (u32, u32)) -> Rung {
        let n_fine = self.depth_resolution_importance;
        let min_coarse = if n_fine > 0 { 4 } else { 2 }.min(self.depth_resolution);
        Rung {
            resolution: self.resolution.div_ceil(res_div).max(8.min(self.resolution)),
            depth_resolution: (self.depth_resolution * coarse.0 / coarse.1).max(min_coarse),
            depth_resolution_importance: if n_fine == 0 {
                0
            } else {
                (n_fine * fine.0 / fine.1).max(2.min(n_fine))
            },
        }
    }

    /// The chosen settings with this rung's resolution and sample counts.
    pub fn apply(&self, chosen: &RenderSettings) -> RenderSettings {
        RenderSettings {
            resolution: self.resolution,
            depth_resolution: self.depth_resolution,
            depth_resolution_importance: self.depth_resolution_importance,
            ..*chosen
        }
    }

    /// `128² · 48+48`, or `128² · 64` without an importance pass.
    pub fn label(&self) -> String {
        if self.depth_resolution_importance == 0 {
            format!("{}² · {}", self.resolution, self.depth_resolution)
        } else {
            format!("{}² · {}+{}", self.resolution, self.depth_resolution, self.depth_resolution_importance)
        }
    }
}

/// (resolution divisor, sample-count divisor) of each exact rung, cheapest first. Each rung costs
/// about 4× the one below, so climbing from any rung to the top adds at most a third of the final
/// frame's time.
const STEPS: [(u32, u32); 4] = [(4, 4), (2, 4), (2, 1), (1, 1)];

/// The baked-only rungs, between the last two exact ones, cheapest first: the chosen resolution
/// with (coarse, fine) samples scaled by these fractions, half of each, then three quarters of the
/// coarse samples and half the fine ones. From the fine field at 128² · 48+48 (which takes a third
/// more coarse samples) they draw 32+24 and 48+24, quicker than its 64+48 frame and less accurate,
/// but far closer to exact 192+192 than 64² · 48+48 shown at 128² (docs/performance.md, "What
/// each drag frame looks like"; bench/history/RESULTS.md, "A second baked-only rung"). The second
/// keeps a drag closer to the still frame when 64+48 just misses the budget; the first serves
/// slower spells. Exact frames skip them: climbing through them would
/// delay the final frame.
const BAKED_STEPS: [((u32, u32), (u32, u32)); 2] = [((1, 2), (1, 2)), ((3, 4), (1, 2))];

/// The rungs for one choice of settings, cheapest first; the last is the chosen quality.
#[derive(Debug, Clone, PartialEq)]
pub struct Ladder {
    pub rungs: Vec<Rung>,
    /// The indices of the rungs only baked frames use (`BAKED_STEPS`, those that cost strictly
    /// between their neighbours); empty when none does.
    pub baked_only: std::ops::Range<usize>,
}

impl Ladder {
    pub fn new(chosen: &RenderSettings) -> Ladder {
        let top = Rung::of(chosen);
        let mut rungs: Vec<Rung> = Vec::with_capacity(STEPS.len() + 1);
        for step in STEPS {
            let rung = top.divided(step);
            if rungs.last() != Some(&rung) {
                rungs.push(rung);
            }
        }
        debug_assert_eq!(rungs.last(), Some(&top));
        // Between the last two exact rungs, each where it costs strictly between the one below
        // and the top (at the renderer's minimum samples scaling changes nothing), so rung 0 is
        // always exact.
        let n = rungs.len();
        let mut baked = Vec::with_capacity(BAKED_STEPS.len());
        if n >= 2 {
            for (coarse, fine) in BAKED_STEPS {
                let rung = top.scaled(1, coarse, fine);
                let below = baked.last().unwrap_or(&rungs[n - 2]).cost();
                if rung.cost() > below && rung.cost() < top.cost() {
                    baked.push(rung);
                }
            }
        }
        let baked_only = n - 1..n - 1 + baked.len();
        rungs.splice(n - 1..n - 1, baked);
        Ladder { rungs, baked_only }
    }

    pub fn top(&self) -> usize {
        self.rungs.len() - 1
    }

    /// Whether exact frames use rung `i` (all but the baked-only rungs).
    pub fn exact(&self, i: usize) -> bool {
        !self.baked_only.contains(&i)
    }

    /// The rung an exact frame refines to after rung `i`: the next exact one (the top at most).
    pub fn next_exact(&self, i: usize) -> usize {
        (i + 1..self.top()).find(|&j| self.exact(j)).unwrap_or(self.top())
    }

    /// Rung `i`'s place among the exact rungs, counted from 1, and their number (the panel's
    /// `refining, step 3 of 4`).
    pub fn exact_step(&self, i: usize) -> (usize, usize) {
        let exact_below = |n: usize| (0..n).filter(|&j| self.exact(j)).count();
        (exact_below(i + 1), exact_below(self.rungs.len()))
    }

    /// The exact rung to render while the camera moves: the most expensive whose predicted time
    /// fits `budget_ms`; the cheapest when none does or nothing has been measured yet.
    pub fn interactive(&self, times: &FrameTimes, budget_ms: f64) -> usize {
        (0..self.rungs.len())
            .rev()
            .filter(|&i| self.exact(i))
            .find(|&i| times.predict(&self.rungs[i]).is_some_and(|ms| ms <= budget_ms))
            .unwrap_or(0)
    }
}

/// Measured render times per rung: the last [`RECENT`] frames of each, predicted by their lower
/// median, so that one slow frame (a load spike) does not move a drag to a lower rung and two of
/// three do; and predictions for rungs not measured yet.
#[derive(Debug, Clone, Default)]
pub struct FrameTimes {
    /// Each rung's recent times, oldest first; the rung measured last is last.
    measured: Vec<(Rung, Vec<f64>)>,
}

/// Rungs remembered (the oldest is forgotten first).
const REMEMBERED: usize = 64;
/// Frames remembered per rung.
const RECENT: usize = 3;

/// The lower median of `times` (not empty): the middle of three, the smaller of two.
fn lower_median(times: &[f64]) -> f64 {
    let mut sorted = times.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted[(sorted.len() - 1) / 2]
}

impl FrameTimes {
    pub fn record(&mut self, rung: Rung, ms: f64) {
        if !ms.is_finite() || ms < 0.0 {
            return;
        }
        let mut recent = match self.measured.iter().position(|(r, _)| *r == rung) {
            Some(i) => self.measured.remove(i).1,
            None => {
                if self.measured.len() == REMEMBERED {
                    self.measured.remove(0);
                }
                Vec::with_capacity(RECENT)
            }
        };
        if recent.len() == RECENT {
            recent.remove(0);
        }
        recent.push(ms);
        self.measured.push((rung, recent));
    }

    /// The rung's measured time, else the time of the measured rung closest in cost, scaled by
    /// the ratio of costs; `None` before any measurement. A rung with fewer than [`RECENT`] frames
    /// takes the lesser of its own time and the rung measured last's, scaled: so one slow frame
    /// (a drag's first, say) does not keep it off for the rest of a drag once the frames drawn
    /// since say it may fit; three frames over the budget do.
    pub fn predict(&self, rung: &Rung) -> Option<f64> {
        if let Some((_, times)) = self.measured.iter().find(|(r, _)| r == rung) {
            let own = lower_median(times);
            return Some(match self.scaled_from_last(rung) {
                Some(scaled) if times.len() < RECENT => own.min(scaled),
                _ => own,
            });
        }
        let cost = rung.cost().max(1.0);
        self.measured
            .iter()
            .min_by(|(a, _), (b, _)| {
                let da = (a.cost().max(1.0) / cost).ln().abs();
                let db = (b.cost().max(1.0) / cost).ln().abs();
                da.total_cmp(&db)
            })
            .map(|(r, times)| lower_median(times) * cost / r.cost().max(1.0))
    }

    /// What a probe (`bake::moving_frame`) expects of `rung`: the lesser of its prediction and the
    /// time of the rung measured last, scaled by the ratio of costs. So a rung whose only frames
    /// were slowed by a spike is tried again once the frames drawn since say the machine is fast.
    pub fn hopeful(&self, rung: &Rung) -> Option<f64> {
        let scaled = self.scaled_from_last(rung)?;
        Some(self.predict(rung).map_or(scaled, |ms| ms.min(scaled)))
    }

    /// The time of the rung measured last, scaled to `rung` by the ratio of costs.
    fn scaled_from_last(&self, rung: &Rung) -> Option<f64> {
        let (last, times) = self.measured.last()?;
        Some(lower_median(times) * rung.cost().max(1.0) / last.cost().max(1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(resolution: u32, coarse: u32, fine: u32) -> RenderSettings {
        RenderSettings {
            resolution,
            depth_resolution: coarse,
            depth_resolution_importance: fine,
            ..Default::default()
        }
    }

    fn labels(l: &Ladder) -> Vec<String> {
        l.rungs.iter().map(Rung::label).collect()
    }

    /// The labels of the rungs exact frames use.
    fn exact_labels(l: &Ladder) -> Vec<String> {
        (0..l.rungs.len()).filter(|&i| l.exact(i)).map(|i| l.rungs[i].label()).collect()
    }

    #[test]
    fn exact_rungs_step_by_four_and_end_at_the_chosen_settings() {
        let l = Ladder::new(&settings(128, 48, 48));
        assert_eq!(exact_labels(&l), ["32² · 12+12", "64² · 12+12", "64² · 48+48", "128² · 48+48"]);
        let exact: Vec<Rung> = (0..l.rungs.len()).filter(|&i| l.exact(i)).map(|i| l.rungs[i]).collect();
        for w in exact.windows(2) {
            assert_eq!(w[1].cost() / w[0].cost(), 4.0);
        }
        // The renderer's minimum sample counts, no importance pass, odd sizes, duplicates merged.
        assert_eq!(
            exact_labels(&Ladder::new(&settings(48, 12, 12))),
            ["12² · 4+3", "24² · 4+3", "24² · 12+12", "48² · 12+12"]
        );
        assert_eq!(
            exact_labels(&Ladder::new(&settings(100, 64, 0))),
            ["25² · 16", "50² · 16", "50² · 64", "100² · 64"]
        );
        assert_eq!(labels(&Ladder::new(&settings(16, 4, 2))), ["8² · 4+2", "16² · 4+2"]);
        for l in [Ladder::new(&settings(16, 4, 2)), Ladder::new(&settings(33, 5, 0))] {
            for r in &l.rungs {
                r.apply(&settings(16, 4, 2)).validate().unwrap();
            }
        }
    }

    #[test]
    fn the_baked_only_rungs_keep_the_resolution_with_fewer_samples() {
        let l = Ladder::new(&settings(128, 48, 48));
        assert_eq!(
            labels(&l),
            ["32² · 12+12", "64² · 12+12", "64² · 48+48", "128² · 24+24", "128² · 36+24", "128² · 48+48"]
        );
        assert_eq!(l.baked_only, 3..5);
        assert_eq!(l.rungs[3].cost() / l.rungs[2].cost(), 2.0);
        assert_eq!(l.rungs[4].cost() / l.rungs[5].cost(), 0.625);
        assert_eq!(labels(&Ladder::new(&settings(100, 64, 0)))[3..5], ["100² · 32", "100² · 48"]);
        // Exact frames climb past them; a baked frame at either refines to the top.
        assert_eq!([0, 1, 2, 3, 4, 5].map(|i| l.next_exact(i)), [1, 2, 5, 5, 5, 5]);
        assert_eq!([0, 2, 5].map(|i| l.exact_step(i)), [(1, 4), (3, 4), (4, 4)]);
        // None where scaling the samples changes nothing (the renderer's minimums) ...
        let small = Ladder::new(&settings(16, 4, 2));
        assert!(small.baked_only.is_empty());
        assert_eq!(small.next_exact(0), 1);
        // ... and only those that cost strictly more than the rung below them: at 5+4 samples
        // three quarters of the coarse ones round up to the renderer's minimum as half do, one rung.
        let one = Ladder::new(&settings(32, 5, 4));
        assert_eq!(labels(&one)[2..], ["16² · 5+4", "32² · 4+2", "32² · 5+4"]);
        assert_eq!(one.baked_only, 3..4);
        for l in [Ladder::new(&settings(48, 12, 12)), Ladder::new(&settings(33, 5, 0))] {
            assert!(!l.baked_only.is_empty() && l.baked_only.end == l.top());
            for i in l.baked_only.clone() {
                assert_eq!(l.rungs[i].resolution, l.rungs[l.top()].resolution);
                assert!(
                    l.rungs[i - 1].cost() < l.rungs[i].cost() && l.rungs[i].cost() < l.rungs[i + 1].cost()
                );
                l.rungs[i].apply(&settings(48, 12, 12)).validate().unwrap();
            }
        }
    }

    #[test]
    fn interactive_rung_is_the_largest_exact_one_predicted_to_fit_the_budget() {
        let l = Ladder::new(&settings(128, 48, 48));
        let mut t = FrameTimes::default();
        assert_eq!(l.interactive(&t, 100.0), 0, "nothing measured: start at the cheapest");
        // 1.2 s at the top predicts 75 ms for 64² · 12+12 (a sixteenth of the cost).
        t.record(l.rungs[l.top()], 1200.0);
        assert_eq!(t.predict(&l.rungs[1]), Some(75.0));
        assert_eq!(l.interactive(&t, 100.0), 1);
        assert_eq!(l.interactive(&t, 2000.0), l.top());
        // 128² · 24+24 (predicted 600 ms) fits 700 ms but is for baked frames: 64² · 48+48.
        assert_eq!(l.interactive(&t, 700.0), 2);
        assert_eq!(l.interactive(&t, 1.0), 0, "nothing fits: the cheapest");
        // A measurement overrides the prediction.
        t.record(l.rungs[1], 180.0);
        assert_eq!(l.interactive(&t, 100.0), 0);
        t.record(l.rungs[1], 20.0);
        assert_eq!(t.predict(&l.rungs[1]), Some(20.0), "the smaller of two");
        assert_eq!(l.interactive(&t, 100.0), 1);
        t.record(l.rungs[1], f64::NAN);
        t.record(l.rungs[1], -1.0);
        assert_eq!(t.predict(&l.rungs[1]), Some(20.0), "not a time: ignored");
    }

    #[test]
    fn one_slow_frame_does_not_demote_a_rung_two_of_three_do() {
        let l = Ladder::new(&settings(128, 48, 48));
        let top = l.rungs[l.top()];
        let mut t = FrameTimes::default();
        for ms in [90.0, 95.0, 300.0] {
            t.record(top, ms);
        }
        assert_eq!(t.predict(&top), Some(95.0), "a spike among three");
        assert_eq!(l.interactive(&t, 100.0), l.top());
        t.record(top, 130.0);
        assert_eq!(t.predict(&top), Some(130.0), "95, 300, 130: a slow spell");
        assert_eq!(l.interactive(&t, 100.0), 2);
        // The oldest drops out: back under the budget after two fast frames.
        t.record(top, 80.0);
        assert_eq!(t.predict(&top), Some(130.0));
        t.record(top, 85.0);
        assert_eq!(t.predict(&top), Some(85.0));
        // Predictions for other rungs scale the same median.
        assert_eq!(t.predict(&l.rungs[2]), Some(85.0 / 4.0));
    }

    #[test]
    fn a_rung_slow_once_is_tried_again_when_the_frames_since_say_it_may_fit() {
        let l = Ladder::new(&settings(128, 48, 48));
        let (half, quarter) = (l.rungs[3], l.rungs[2]); // 128² · 24+24 and 64² · 48+48
        let mut t = FrameTimes::default();
        t.record(half, 112.0);
        assert_eq!(t.predict(&half), Some(112.0), "measured last: its own time");
        // The frames at a quarter of the cost since (48 ms) say about 96 ms: tried again.
        t.record(quarter, 48.0);
        assert_eq!(t.predict(&half), Some(96.0));
        t.record(half, 110.0);
        t.record(quarter, 48.0);
        assert_eq!(t.predict(&half), Some(96.0), "two frames over the budget: still hopeful");
        // A third frame over the budget: its own lower median, whatever the others say.
        t.record(half, 111.0);
        t.record(quarter, 40.0);
        assert_eq!(t.predict(&half), Some(111.0));
        // A rung with fewer frames is never predicted slower than its own time.
        let mut fast = FrameTimes::default();
        fast.record(half, 50.0);
        fast.record(quarter, 45.0);
        assert_eq!(fast.predict(&half), Some(50.0));
    }

    #[test]
    fn a_probe_hopes_from_the_rung_measured_last() {
        let l = Ladder::new(&settings(128, 48, 48));
        let (top, quarter) = (l.rungs[l.top()], l.rungs[2]);
        let mut t = FrameTimes::default();
        assert_eq!(t.hopeful(&top), None);
        for _ in 0..3 {
            t.record(top, 400.0);
        }
        assert_eq!(t.hopeful(&top), Some(400.0));
        // Frames at a quarter of the cost since: 30 ms says the top would take about 120. Its
        // three slow frames keep its prediction (a rung with fewer would take the 120 too).
        t.record(quarter, 30.0);
        assert_eq!(t.predict(&top), Some(400.0));
        assert_eq!(t.hopeful(&top), Some(120.0));
        // Its own time when that is less.
        t.record(top, 90.0);
        t.record(top, 95.0);
        t.record(quarter, 40.0);
        assert_eq!(t.hopeful(&top), Some(95.0));
    }
}

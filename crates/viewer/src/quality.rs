//! The quality ladder: while the camera moves, the viewer renders at the most expensive rung whose
//! predicted time fits the frame budget; once it stops, it climbs the ladder one rung per UI frame
//! up to the chosen settings. Rungs change only the resolution and sample counts, which reach the
//! kernel through its `Params` uniform and the dispatch size, so no rung builds a new pipeline.

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

/// (resolution divisor, sample-count divisor) of each rung, cheapest first. Each rung costs about
/// 4× the one below, so climbing from any rung to the top adds at most a third of the final
/// frame's time.
const STEPS: [(u32, u32); 4] = [(4, 4), (2, 4), (2, 1), (1, 1)];

/// The rungs for one choice of settings, cheapest first; the last is the chosen quality.
#[derive(Debug, Clone, PartialEq)]
pub struct Ladder {
    pub rungs: Vec<Rung>,
}

impl Ladder {
    pub fn new(chosen: &RenderSettings) -> Ladder {
        let top = Rung::of(chosen);
        let fine = top.depth_resolution_importance;
        // The renderer's limits: an importance pass needs 4 coarse samples and 2 fine ones.
        let min_coarse = if fine > 0 { 4 } else { 2 }.min(top.depth_resolution);
        let mut rungs: Vec<Rung> = Vec::with_capacity(STEPS.len());
        for (res_div, samples_div) in STEPS {
            let rung = Rung {
                resolution: top.resolution.div_ceil(res_div).max(8.min(top.resolution)),
                depth_resolution: (top.depth_resolution / samples_div).max(min_coarse),
                depth_resolution_importance: if fine == 0 {
                    0
                } else {
                    (fine / samples_div).max(2.min(fine))
                },
            };
            if rungs.last() != Some(&rung) {
                rungs.push(rung);
            }
        }
        debug_assert_eq!(rungs.last(), Some(&top));
        Ladder { rungs }
    }

    pub fn top(&self) -> usize {
        self.rungs.len() - 1
    }

    /// The rung to render while the camera moves: the most expensive whose predicted time fits
    /// `budget_ms`; the cheapest when none does or nothing has been measured yet.
    pub fn interactive(&self, times: &FrameTimes, budget_ms: f64) -> usize {
        (0..self.rungs.len())
            .rev()
            .find(|&i| times.predict(&self.rungs[i]).is_some_and(|ms| ms <= budget_ms))
            .unwrap_or(0)
    }
}

/// Measured render times per rung (a moving average, so a load spike fades), and predictions
/// for rungs not measured yet.
#[derive(Debug, Clone, Default)]
pub struct FrameTimes {
    measured: Vec<(Rung, f64)>,
}

/// Rungs remembered (the oldest is forgotten first).
const REMEMBERED: usize = 64;

impl FrameTimes {
    pub fn record(&mut self, rung: Rung, ms: f64) {
        if !ms.is_finite() || ms < 0.0 {
            return;
        }
        if let Some(i) = self.measured.iter().position(|(r, _)| *r == rung) {
            let (_, old) = self.measured.remove(i);
            self.measured.push((rung, 0.5 * old + 0.5 * ms));
        } else {
            if self.measured.len() == REMEMBERED {
                self.measured.remove(0);
            }
            self.measured.push((rung, ms));
        }
    }

    /// The rung's measured time, else the time of the measured rung closest in cost, scaled by
    /// the ratio of costs; `None` before any measurement.
    pub fn predict(&self, rung: &Rung) -> Option<f64> {
        if let Some((_, ms)) = self.measured.iter().find(|(r, _)| r == rung) {
            return Some(*ms);
        }
        let cost = rung.cost().max(1.0);
        self.measured
            .iter()
            .min_by(|(a, _), (b, _)| {
                let da = (a.cost().max(1.0) / cost).ln().abs();
                let db = (b.cost().max(1.0) / cost).ln().abs();
                da.total_cmp(&db)
            })
            .map(|(r, ms)| ms * cost / r.cost().max(1.0))
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

    #[test]
    fn ladder_steps_by_four_and_ends_at_the_chosen_settings() {
        let l = Ladder::new(&settings(128, 48, 48));
        assert_eq!(labels(&l), ["32² · 12+12", "64² · 12+12", "64² · 48+48", "128² · 48+48"]);
        for w in l.rungs.windows(2) {
            assert_eq!(w[1].cost() / w[0].cost(), 4.0);
        }
        // The renderer's minimum sample counts, no importance pass, odd sizes, duplicates merged.
        assert_eq!(
            labels(&Ladder::new(&settings(48, 12, 12))),
            ["12² · 4+3", "24² · 4+3", "24² · 12+12", "48² · 12+12"]
        );
        assert_eq!(
            labels(&Ladder::new(&settings(100, 64, 0))),
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
    fn interactive_rung_is_the_largest_predicted_to_fit_the_budget() {
        let l = Ladder::new(&settings(128, 48, 48));
        let mut t = FrameTimes::default();
        assert_eq!(l.interactive(&t, 100.0), 0, "nothing measured: start at the cheapest");
        // 1.2 s at the top predicts 75 ms for 64² · 12+12 (a sixteenth of the cost).
        t.record(l.rungs[3], 1200.0);
        assert_eq!(t.predict(&l.rungs[1]), Some(75.0));
        assert_eq!(l.interactive(&t, 100.0), 1);
        assert_eq!(l.interactive(&t, 2000.0), 3);
        assert_eq!(l.interactive(&t, 1.0), 0, "nothing fits: the cheapest");
        // A measurement overrides the prediction (and is averaged with later ones).
        t.record(l.rungs[1], 180.0);
        assert_eq!(l.interactive(&t, 100.0), 0);
        t.record(l.rungs[1], 20.0);
        assert_eq!(t.predict(&l.rungs[1]), Some(100.0));
        assert_eq!(l.interactive(&t, 100.0), 1);
        t.record(l.rungs[1], f64::NAN);
        assert_eq!(t.predict(&l.rungs[1]), Some(100.0));
    }
}

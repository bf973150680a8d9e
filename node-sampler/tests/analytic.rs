//! The analytic suite (issue 19) at the standard preset: every closed-form quantity of
//! `scenes/analytic/` against its tolerance (each stated and justified at its measurement in
//! `mwb_sampler::analytic`).
//!
//! Where rapier does not meet the justified tolerance, the case is listed here as a documented
//! failure with the band its error was measured in, instead of loosening the tolerance until it
//! passes: the test then fails if the simulator gets worse *or* better than documented (update
//! docs/fidelity.md and this table with it).

use mwb_core::scene::SimPreset;
use mwb_sampler::analytic::{self, AnalyticCase, AnalyticScene};

/// What docs/fidelity.md says of a case at the standard preset.
#[derive(Debug, Clone, Copy)]
enum Documented {
    /// Within its tolerance.
    Passes,
    /// Outside its tolerance, with the error (measured − expected, in the case's unit) in this
    /// band. Bands are about ±25 % around the measured error.
    Fails {
        error: (f64, f64),
        why: &'static str,
    },
}

/// Rapier's restitution loses about 1.2 % of the rebound height per bounce beyond e² at
/// standard (its soft contact bias and the restitution being applied at the substep where the
/// contact becomes active): apex 1 is still within 3 %, apex 2 is 3.2 % low, apex 3 6.1 % low.
const BOUNCE_WHY: &str = "soft contacts lose ~1.2 % of each rebound beyond e²";
/// Ten boxes on soft contacts: each contact sits inside by an amount growing with its load.
const STACK_WHY: &str = "soft contacts (30 Hz, ζ = 10) compress under the stack's weight";

const STANDARD: &[(&str, &str, Documented)] = &[
    ("projectile", "apex", Documented::Passes),
    ("projectile", "range", Documented::Passes),
    ("sliding", "stop distance", Documented::Passes),
    ("bounce", "apex 1", Documented::Passes),
    (
        "bounce",
        "apex 2",
        Documented::Fails {
            error: (-0.017, -0.0124),
            why: BOUNCE_WHY,
        },
    ),
    (
        "bounce",
        "apex 3",
        Documented::Fails {
            error: (-0.020, -0.012),
            why: BOUNCE_WHY,
        },
    ),
    ("rest", "rest height", Documented::Passes),
    ("incline", "acceleration", Documented::Passes),
    ("rolling", "rolling speed", Documented::Passes),
    ("pendulum", "period", Documented::Passes),
    (
        "stack",
        "sag",
        Documented::Fails {
            error: (0.018, 0.030),
            why: STACK_WHY,
        },
    ),
    (
        "stack",
        "lateral drift",
        Documented::Fails {
            error: (0.0025, 0.0050),
            why: STACK_WHY,
        },
    ),
];

fn suite(preset: SimPreset) -> Vec<AnalyticCase> {
    analytic::run_suite(preset).unwrap_or_else(|e| panic!("{preset}: {e}"))
}

fn print(preset: SimPreset, cases: &[AnalyticCase]) {
    for c in cases {
        eprintln!(
            "{preset} | {} | {} | {:.6} {} | {:.6} | {:+.3e} | {:.3e} | {}",
            c.name,
            c.quantity,
            c.expected,
            c.unit,
            c.measured,
            c.error,
            c.tolerance,
            if c.passes() { "pass" } else { "FAIL" }
        );
    }
}

#[test]
fn the_suite_at_standard_is_as_documented() {
    let cases = suite(SimPreset::Standard);
    print(SimPreset::Standard, &cases);
    assert_eq!(
        cases.len(),
        STANDARD.len(),
        "every measured case is documented"
    );
    for (c, &(name, quantity, doc)) in cases.iter().zip(STANDARD) {
        assert_eq!((c.name, c.quantity), (name, quantity));
        assert!(c.measured.is_finite(), "{name} {quantity}: {c:?}");
        match doc {
            Documented::Passes => assert!(
                c.passes(),
                "{name} {quantity}: error {:e} {} outside ±{:e}",
                c.error,
                c.unit,
                c.tolerance
            ),
            Documented::Fails {
                error: (lo, hi),
                why,
            } => {
                assert!(
                    !c.passes(),
                    "{name} {quantity} now passes (error {:e}): documented as failing ({why}); \
                     update docs/fidelity.md",
                    c.error
                );
                assert!(
                    (lo..=hi).contains(&c.error),
                    "{name} {quantity}: error {:e} {} outside its documented band [{lo}, {hi}] ({why})",
                    c.error,
                    c.unit
                );
            }
        }
    }
}

/// Free flight is the integrator's alone: its bias is `g·h·t/2` for the substep `h`, so the
/// projectile's error shrinks with the substeps, draft (1) > standard (4) > final (8), in
/// proportion (within 10 %).
#[test]
fn free_flight_error_shrinks_with_the_substeps() {
    let apex = |preset: SimPreset| {
        let scene = {
            let mut s = AnalyticScene::Projectile
                .scene()
                .unwrap_or_else(|e| panic!("{e}"));
            s.settings = preset.apply(&s.settings);
            s
        };
        let substeps = f64::from(scene.settings.solver_iterations);
        let cases = AnalyticScene::Projectile
            .measure(&scene)
            .unwrap_or_else(|e| panic!("{preset}: {e}"));
        let apex = cases
            .iter()
            .find(|c| c.quantity == "apex")
            .unwrap_or_else(|| panic!("{preset}: no apex"));
        (apex.error, substeps)
    };
    let (draft, n_draft) = apex(SimPreset::Draft);
    let (standard, n_standard) = apex(SimPreset::Standard);
    let (fin, n_final) = apex(SimPreset::Final);
    eprintln!("apex error: draft {draft:e}, standard {standard:e}, final {fin:e}");
    assert!(draft < standard && standard < fin && fin < 0.0);
    for (e, n) in [(standard, n_standard), (fin, n_final)] {
        let ratio = (e * n) / (draft * n_draft);
        assert!((ratio - 1.0).abs() < 0.1, "error × substeps ratio {ratio}");
    }
}

/// The analytic scenes are scenes like any other: they parse, and they switch §4.1
/// perturbations off (the closed forms know nothing of them).
#[test]
fn the_analytic_scenes_turn_perturbations_off() {
    for s in AnalyticScene::ALL {
        let scene = s.scene().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(scene.settings.alpha, 0.0, "{}", s.name());
        assert_eq!(scene.name, format!("analytic-{}", s.name()));
    }
}

/// The limit checks know the suite: they flag the stack (its sag is the documented failure)
/// and nothing else. The bounce's documented failure (1.1 % per bounce beyond e²) is below
/// what the restitution check warns about (e ≥ 0.95, bounces that are meant to last).
#[test]
fn the_limit_checks_flag_the_stack_and_nothing_else() {
    for s in AnalyticScene::ALL {
        let scene = s.scene().unwrap_or_else(|e| panic!("{e}"));
        let findings = mwb_sampler::limits::check(&scene);
        let fields: Vec<&str> = findings.iter().map(|f| f.field).collect();
        let expected: &[&str] = match s {
            AnalyticScene::Stack => &["position"],
            _ => &[],
        };
        assert_eq!(fields, expected, "{}: {findings:#?}", s.name());
    }
}

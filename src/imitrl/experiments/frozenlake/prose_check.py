"""The section's prose claims, checked against the study's measured and exact numbers."""

from __future__ import annotations

from collections.abc import Callable

from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.experiments.frozenlake.report import Report

__all__ = ["prose_checks"]

# (eps, T) of a chain panel -> (the prose's claim, whether the exact ratio bears it out)
_CHAIN_CLAIMS: dict[tuple[float, int], tuple[str, Callable[[float], bool]]] = {
    (0.05, 10): (
        "cloned and recovering already five times apart at T = 10",
        lambda x: abs(x - 5.0) < 0.5,
    ),
    (0.01, 64): (
        "at T = 64 the gap between the rates has grown past thirtyfold",
        lambda x: x > 30.0,
    ),
}


class _Checks:
    """Prints each claim's verdict and collects it for results.json."""

    def __init__(self, report: Report) -> None:
        self.report = report
        self.rows: list[dict] = []

    def check(
        self, claim: str, printed: float | None, exact: float, agrees: bool, note: str = ""
    ) -> None:
        verdict = "agrees" if agrees else "DISAGREES"
        measured = "undefined" if printed is None else f"{printed:.4g}"
        self.report.line(
            f"- {claim}: measured {measured}, exact {exact:.4g} -> {verdict}{'; ' + note if note else ''}"
        )
        self.rows.append(
            {
                "claim": claim,
                "measured": printed,
                "exact": exact,
                "agrees": bool(agrees),
                "note": note,
            }
        )


def _evaluation_claims(checks: _Checks, ev: dict) -> None:
    """Section 3's success rates, and "the clone fails three times as often as the expert"."""
    for name in ("expert", "clone"):
        if name in ev:
            e = ev[name]
            # slack: at 0 (or all) successes the Wilson bound is a rounding error past 0 (1)
            inside = e["ci"][0] - 1e-12 <= e["exact"] <= e["ci"][1] + 1e-12
            checks.check(
                f"{name} success rate {e['rate']:.1%}",
                e["rate"],
                e["exact"],
                inside,
                "exact value inside the 95% interval"
                if inside
                else "exact value outside the 95% interval",
            )
    if "expert" not in ev or "clone" not in ev:
        return
    if min(1 - ev["expert"]["rate"], 1 - ev["expert"]["exact"]) <= 0:
        checks.report.line(
            "- the clone fails three times as often as the expert: undefined, the expert never fails"
        )
        return
    fail_ratio = (1 - ev["clone"]["rate"]) / (1 - ev["expert"]["rate"])
    fail_exact = (1 - ev["clone"]["exact"]) / (1 - ev["expert"]["exact"])
    checks.check(
        "the clone fails three times as often as the expert",
        fail_ratio,
        fail_exact,
        abs(fail_exact - 3) < 0.5,
    )


def _chain_claims(checks: _Checks, panels: list[dict]) -> None:
    """Section 5's ratios of lost returns, for the panels the prose speaks of."""
    for c in panels:
        if (c["eps"], c["T"]) in _CHAIN_CLAIMS:
            claim, holds = _CHAIN_CLAIMS[(c["eps"], c["T"])]
            checks.check(
                claim,
                c["ratio"],
                c["ratio_exact"],
                holds(c["ratio_exact"]),
                "ratio of lost returns, cloned / recovering",
            )


def _divergence_claim(checks: _Checks, div: dict) -> None:
    """Section 6's mass in the worst hole by step 20 (where the run's ``--tv-steps`` reach
    it: the distributions are computed up to their largest)."""
    if "worst_hole_at_20" in div:
        h = str(div["worst_hole_at_20"])
        mass = div["hole_mass_at_20"][h]["clone"]
        checks.check(
            f"the clone parks 22 percent of its mass in hole {h} by step 20",
            mass,
            mass,
            abs(mass - 0.22) < 0.01,
            "exact kernel evolution",
        )


def _dagger_claim(checks: _Checks, rounds: list[dict], results: dict) -> None:
    """Section 7: one round after the demonstrations, the learner matches the expert."""
    if len(rounds) > 1:
        e = results["expert"]["exact_success"]
        checks.check(
            "one DAgger round later the clone matches the expert",
            rounds[1]["rate"],
            rounds[1]["exact"],
            abs(rounds[1]["exact"] - e) < 0.01,
            f"expert exact {e:.4f}",
        )


def _irl_claims(checks: _Checks, fit: dict, expert: float) -> None:
    """Section 8 against the closing pointer: "inferring the reward function under which the
    demonstrations are (softly) optimal and planning against it"."""
    if not fit:
        return
    share = fit["demonstrations_argmax"]
    checks.check(
        "maximum-entropy IRL infers a reward under which the demonstrations are softly optimal",
        share,
        share,
        share == 1.0,
        "share of demonstrated actions that are the soft-optimal policy's most likely action",
    )
    checks.check(
        "planning against the inferred reward recovers the expert",
        fit["exact_success_greedy"],
        expert,
        abs(fit["exact_success_greedy"] - expert) < 0.01,
        "exact success of the greedy plan vs the expert's",
    )


def prose_checks(ctx: StudyContext) -> None:
    """Where the section's prose and the exact numbers agree or not."""
    r, rep = ctx.report.results, ctx.report
    rep.section("Prose vs exact values")
    checks = _Checks(rep)
    faithful = ctx.config.protocol == "faithful"
    if not faithful:
        rep.line(
            "(the batched protocol draws other datasets: only the draw-independent claims are checked)"
        )
    _evaluation_claims(checks, r.get("evaluation", {}) if faithful else {})
    _chain_claims(checks, r.get("chain", {}).get("panels", []))
    _divergence_claim(checks, r.get("divergence", {}) if faithful else {})
    _dagger_claim(checks, r.get("dagger", {}).get("rounds", []) if faithful else [], r)
    irl_fit = r.get("irl", {}).get("fit", {}) if faithful else {}  # from section 1's draw
    _irl_claims(checks, irl_fit, r["expert"]["exact_success"])
    rep.set("prose_checks", checks.rows)

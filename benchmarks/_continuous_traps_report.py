"""``continuous_traps.py``'s tables, one function per trap, from its results dict."""

from __future__ import annotations

import _report
from imitrl.evaluation import t_interval


def markdown(results: dict, cfg) -> str:
    return "\n".join(
        [
            f"Total time {results['seconds']:.0f} s (1 torch thread).",
            "",
            float64_table(results),
            "",
            vector_table(results, cfg),
            "",
            frame_skip_table(results, cfg),
            "",
            bang_bang_table(results, cfg),
            "",
            startup_table(results, cfg),
            "",
            f"CostlyPendulum-v0 is Pendulum-v1 with {results['costly_step_s'] * 1e3:.0f} ms of "
            "CPU work per step, a stand-in for an expensive simulator. "
            + parallel_verdict(results),
        ]
    )


def float64_table(results: dict) -> str:
    rows = [
        [
            _report.env_label(k),
            v["gymenv_dtype"],
            f"`{v['float32_policy_on_gymenv']}`",
            v["make_env_dtype"],
        ]
        for k, v in results["float64"].items()
    ]
    return _report.section(
        "**1. float64 observations** (a float32 MLP fed a `GymEnv` observation):",
        _report.table(["env", "GymEnv obs", "float32 policy on it", "make_env obs"], rows),
    )


def vector_table(results: dict, cfg) -> str:
    rows = [
        [k, v["episode_ends"], v["all_zero_final_obs"], f"{v['build_s']:.1f}"]
        for k, v in results["vector_final_obs"].items()
    ]
    header = ["env", "episode ends", "all-zero final observations", "build s"]
    return _report.section(
        f"**2. final observations of vectorised {_report.env_label(cfg.vector_env)}** "
        f"(4 lanes, {cfg.vector_steps} random-action steps):",
        _report.table(header, rows),
    )


def frame_skip_table(results: dict, cfg) -> str:
    rows = []
    for env_id, per in results["frame_skip"].items():
        for k, entry in per.items():
            again = entry.get("re-identified for k steps")
            rows.append(
                [
                    _report.env_label(env_id),
                    k,
                    f"{entry['one-step expert']:.1f}",
                    "-" if again is None else f"{again:.1f}",
                    f"{entry['uniform random']:.1f}",
                ]
            )
    header = [
        "env",
        "k",
        "expert tuned for one step",
        "re-identified for k steps (`action_repeat=k`)",
        "uniform random",
    ]
    return _report.section(
        f"**3. frame_skip** (each action held k steps; mean return of "
        f"{cfg.frame_skip_episodes} episodes from the same initial states):",
        _report.table(header, rows),
    )


def bang_bang_table(results: dict, cfg) -> str:
    rows = []
    rounds = cfg.relabel_rounds + 1
    for name, seeds in results["bang_bang"].items():
        spin = [f"{t_interval([s['spinning'][k] for s in seeds])[0]:.2f}" for k in range(rounds)]
        spinning_rounds = sum(x >= 0.2 for s in seeds for x in s["spinning"][1:])
        rows.append(
            [
                name,
                *spin,
                f"{spinning_rounds}/{len(seeds) * (rounds - 1)}",
                f"{sum(s['spinning'][-1] >= 0.2 for s in seeds)}/{len(seeds)}",
                _report.fmt_ci(t_interval([s["return"][-1] for s in seeds]), 0),
            ]
        )
    header = [
        "expert, beta",
        *[f"spinning r{k}" for k in range(rounds)],
        "(seed, round >= 1) spinning >= 20%",
        f"seeds spinning >= 20% at r{rounds - 1}",
        f"return r{rounds - 1}",
    ]
    return _report.section(
        f"**4. DAgger on {_report.env_label(cfg.dagger_env)} with a bang-bang expert** "
        f"({cfg.seeds} seeds, one demonstration, {cfg.episodes_per_round} episodes per "
        f"round unless stated, {cfg.fit_steps} fit steps, {cfg.eval_episodes} "
        "evaluation episodes; spinning = at least one full turn in the second half of an "
        "episode; mean [95% t-interval over seeds]):",
        _report.table(header, rows),
    )


def _frames_to_pay(results: dict, key: str) -> float | None:
    """Frames after which a parallel env's extra start-up is paid back (None: never)."""
    v = results["startup"][key]
    base = results["startup"][key.replace(" parallel", " in-process")]
    saved = 1 / base["frames_per_s"] - 1 / v["frames_per_s"]  # seconds per frame
    return (v["start_s"] - base["start_s"]) / saved if saved > 0 else None


def startup_table(results: dict, cfg) -> str:
    rows = []
    for k, v in results["startup"].items():
        pays = "-"
        if k.endswith(" parallel"):
            frames = _frames_to_pay(results, k)
            pays = "never (slower per frame)" if frames is None else f"{frames:.0f}"
        rows.append(
            [k, f"{v['start_s']:.2f}", f"{v['close_s']:.2f}", f"{v['frames_per_s']:.0f}", pays]
        )
    header = ["env x lanes", "start s", "close s", "frames/s", "pays after (frames)"]
    return _report.section(
        f"**5. start-up cost of `parallel=True`** ({cfg.startup_steps} batched steps of "
        "zero actions):",
        _report.table(header, rows),
    )


def parallel_verdict(results: dict) -> str:
    paying = [
        k.replace(" parallel", "")
        for k in results["startup"]
        if k.endswith(" parallel") and _frames_to_pay(results, k) is not None
    ]
    if paying:
        return f"Here `parallel=True` paid off only for: {', '.join(paying)}."
    return (
        "Here `parallel=True` never paid off: the inter-process round trip cost "
        "more than it saved (on a 2-core machine the workers also compete with the "
        "main process); keep `parallel=False` unless a step costs far more and idle "
        "cores are available."
    )

"""Are ``imitrl compare``'s rules calibrated? Checked against exact success probabilities.

On slippery FrozenLake (imitrl's ``TabularEnv``, 100-step episodes) the success
probability of any tabular policy is known exactly (``imitrl.tabular.success_probability``).
The policies: ``pi_eps`` plays the value-iteration expert's action with probability
``1 - eps`` and a uniform one otherwise. Two scenarios, ``comparisons`` comparisons each:

* null: ``pi_0.3`` against itself (the true difference is 0);
* alternative: ``pi_0.3`` against ``pi_0.6`` (the true difference is exact).

Each comparison is ``budget`` episode pairs played by the env (each side its own
episodes: the outcomes' draws are independent, the case where pairing helps least), on
which imitrl's two rules decide at ``alpha``: the fixed-size paired Student-t test
(``imitrl compare``; at each size ``n`` on the first ``n`` pairs) and the sequential
betting confidence sequence (``imitrl compare --sequential``, stopping when it excludes
0, at most ``budget`` pairs). Reported: the false-positive rate (null), the power
(alternative), the coverage of the exact difference by the intervals, the sequential
rule's mean episodes, and the fixed-size test's size of equal power.

    python benchmarks/compare_calibration.py            # full run, refreshes the README block
    python benchmarks/compare_calibration.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import ExplorationType

import _report
from _common import lake
from imitrl.envs import TabularEnv
from imitrl.evaluation.compare import log_capital
from imitrl.evaluation.evaluate import tabular_success, wilson_interval
from imitrl.evaluation.statistics import student_t_quantile
from imitrl.runtime import episode_returns
from imitrl.tabular import success_probability

NAME = "compare_calibration"


@dataclass(frozen=True)
class Config:
    comparisons: int = 10_000
    budget: int = 400
    """episode pairs a comparison may use"""
    alpha: float = 0.05
    eps_a: float = 0.3
    eps_b: float = 0.6
    horizon: int = 100
    chunk: int = 500_000
    """episodes played at once (lanes)"""


QUICK = Config(comparisons=200, budget=100, chunk=20_000)


def policy_table(q: torch.Tensor, eps: float) -> torch.Tensor:
    """``[S, A]``: the greedy action of ``q`` with probability ``1 - eps``, uniform else."""
    n_actions = q.shape[1]
    probs = torch.full_like(q, eps / n_actions, dtype=torch.float64)
    probs[torch.arange(q.shape[0]), q.argmax(1)] += 1 - eps
    return probs


class _Sample(torch.nn.Module):
    def __init__(self, probs: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("probs", probs.float())

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.multinomial(self.probs[obs.reshape(-1)], 1).reshape(obs.shape)


def outcomes(mdp, probs: torch.Tensor, n: int, seed: int, cfg: Config) -> torch.Tensor:
    """``[n]`` float64 successes of ``n`` episodes of the table policy ``probs``."""
    out = []
    policy = TensorDictModule(_Sample(probs), in_keys=["observation"], out_keys=["action"])
    for k, start in enumerate(range(0, n, cfg.chunk)):
        lanes = min(cfg.chunk, n - start)
        env = TabularEnv(mdp, batch_size=(lanes,), max_steps=cfg.horizon, seed=seed + k)
        got = episode_returns(env, policy, lanes, exploration=ExplorationType.RANDOM,
                              seed=seed + k, success_fn=tabular_success(env))  # fmt: skip
        assert got.success is not None
        out.append(got.success.double())
        print(f"  {start + lanes:,}/{n:,} episodes", file=sys.stderr, flush=True)
    return torch.cat(out)


def fixed_rule(d: torch.Tensor, n: int, alpha: float, truth: float) -> dict:
    """The paired t test and interval on the first ``n`` pairs of each row of ``d``."""
    x = d[:, :n]
    mean, sd = x.mean(1), x.std(1)
    half = student_t_quantile(1 - alpha / 2, n - 1) * sd / math.sqrt(n)
    lo, hi = mean - half, mean + half
    return {"reject": ((lo > 0) | (hi < 0)).double().mean().item(),
            "covers": ((lo <= truth) & (truth <= hi)).double().mean().item()}  # fmt: skip


def sequential_rule(d: torch.Tensor, alpha: float, truth: float) -> dict:
    """The betting confidence sequence on each row of ``d`` (``[K, budget]``)."""
    y = (d + 1) / 2  # a success difference lies in [-1, 1]
    m = torch.tensor([0.5, (truth + 1) / 2], dtype=torch.float64)
    crossed = log_capital(y, m, alpha) >= math.log(1 / alpha)  # [K, n, 2]
    rejects = crossed[:, :, 0].any(1)
    first = torch.where(rejects, crossed[:, :, 0].double().argmax(1) + 1, d.shape[1])
    return {"reject": rejects.double().mean().item(),
            "covers": (~crossed[:, :, 1].any(1)).double().mean().item(),  # at every stop
            "mean_episodes": first.double().mean().item()}  # fmt: skip


def scenario(mdp, q, eps_b: float, cfg: Config, seed: int) -> dict:
    probs_a, probs_b = policy_table(q, cfg.eps_a), policy_table(q, eps_b)
    p_a = success_probability(mdp, probs_a, cfg.horizon)
    p_b = success_probability(mdp, probs_b, cfg.horizon)
    n = cfg.comparisons * cfg.budget
    a = outcomes(mdp, probs_a, n, seed, cfg)
    b = outcomes(mdp, probs_b, n, seed + 1_000_000, cfg)
    d = (a - b).reshape(cfg.comparisons, cfg.budget)
    truth = p_a - p_b
    sizes = sorted({max(2, int(cfg.budget * f)) for f in (0.05, 0.1, 0.15, 0.2, 0.25, 0.3,
                    0.35, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)})  # fmt: skip
    return {
        "eps": [cfg.eps_a, eps_b], "exact": [p_a, p_b], "truth": truth,
        "estimated": [a.mean().item(), b.mean().item()],
        "estimated_ci": [wilson_interval(int(a.sum()), n), wilson_interval(int(b.sum()), n)],
        "fixed": {n_: fixed_rule(d, n_, cfg.alpha, truth) for n_ in sizes},
        "sequential": sequential_rule(d, cfg.alpha, truth),
    }  # fmt: skip


def equal_power_size(fixed: dict, power: float) -> float | None:
    """The pairs at which the fixed test's measured power reaches ``power``: linear
    interpolation between the measured sizes (None beyond the largest)."""
    curve = sorted((n, r["reject"]) for n, r in fixed.items())
    for (n0, p0), (n1, p1) in zip(curve, curve[1:]):
        if p0 < power <= p1:
            return n0 + (power - p0) / (p1 - p0) * (n1 - n0)
    return float(curve[0][0]) if curve and curve[0][1] >= power else None


def figure(null: dict, alt: dict, summ: dict, cfg: Config, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.6))
    sizes = sorted(alt["fixed"])
    left.plot(
        sizes,
        [alt["fixed"][n]["reject"] for n in sizes],
        "o-",
        label="fixed: paired t, power at n pairs",
    )
    left.plot([summ["sequential_mean_episodes"]], [summ["power_sequential"]], "s", ms=9,
              label="sequential: power, mean pairs used")  # fmt: skip
    if summ["fixed_size_of_equal_power"] is not None:
        left.axvline(summ["fixed_size_of_equal_power"], color="grey", ls=":",
                     label="fixed size of equal power")  # fmt: skip
    left.set_xlabel("episode pairs")
    left.set_ylabel(f"power (exact difference {alt['truth']:+.3f})")
    left.set_title("alternative: pi_0.3 vs pi_0.6")
    left.legend(fontsize=8, loc="lower right")
    rates = [summ["false_positive_fixed"], summ["false_positive_sequential"]]
    covers = [summ["coverage_fixed_alt"], summ["coverage_sequential_alt"]]
    xs = [0, 1]
    right.bar([x - 0.2 for x in xs], rates, 0.4, label="false-positive rate (null)")
    right.bar([x + 0.2 for x in xs], [1 - c for c in covers], 0.4,
              label="1 - coverage of the exact difference (alternative)")  # fmt: skip
    right.axhline(cfg.alpha, color="k", ls="--", lw=1, label=f"alpha = {cfg.alpha}")
    right.set_xticks(xs, ["fixed: paired t", "sequential: betting CS"])
    right.set_title(f"error rates, {cfg.comparisons:,} comparisons each")
    right.set_ylim(0, 2 * cfg.alpha)
    right.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def summary(null: dict, alt: dict, cfg: Config) -> dict:
    full = cfg.budget
    seq_power = alt["sequential"]["reject"]
    equal = equal_power_size(alt["fixed"], seq_power)
    saved = None if equal is None else 1 - alt["sequential"]["mean_episodes"] / equal
    return {
        "false_positive_fixed": null["fixed"][full]["reject"],
        "false_positive_sequential": null["sequential"]["reject"],
        "coverage_fixed_null": null["fixed"][full]["covers"],
        "coverage_fixed_alt": alt["fixed"][full]["covers"],
        "coverage_sequential_null": null["sequential"]["covers"],
        "coverage_sequential_alt": alt["sequential"]["covers"],
        "power_fixed_full": alt["fixed"][full]["reject"],
        "power_sequential": seq_power,
        "sequential_mean_episodes": alt["sequential"]["mean_episodes"],
        "fixed_size_of_equal_power": equal,
        "episodes_saved": saved,
    }


def markdown(cfg: Config, null: dict, alt: dict, summ: dict, wall: float) -> str:
    k = cfg.comparisons
    se = lambda p: math.sqrt(p * (1 - p) / k)  # noqa: E731  (Monte Carlo error of a rate)
    rows = [
        ["false-positive rate (null)", f"{summ['false_positive_fixed']:.4f} ± {se(cfg.alpha):.4f}",
         f"{summ['false_positive_sequential']:.4f}"],
        ["coverage of the exact difference (null)", f"{summ['coverage_fixed_null']:.4f}",
         f"{summ['coverage_sequential_null']:.4f} (at every stop)"],
        ["coverage of the exact difference (alternative)", f"{summ['coverage_fixed_alt']:.4f}",
         f"{summ['coverage_sequential_alt']:.4f} (at every stop)"],
        ["power (alternative)", f"{summ['power_fixed_full']:.4f} at {cfg.budget} pairs",
         f"{summ['power_sequential']:.4f}, {summ['sequential_mean_episodes']:.1f} pairs on average"],
        ["fixed size of the sequential rule's power",
         "-" if summ["fixed_size_of_equal_power"] is None else f"{summ['fixed_size_of_equal_power']:.0f} pairs (interpolated)",
         "-" if summ["episodes_saved"] is None else f"{100 * summ['episodes_saved']:+.0f}% episodes saved"],
    ]  # fmt: skip
    curve = ", ".join(f"{n}: {r['reject']:.3f}" for n, r in sorted(alt["fixed"].items()))
    return _report.section(
        "Calibration of imitrl compare against exact success probabilities (compare_calibration.py)",
        f"`python benchmarks/compare_calibration.py` ({wall / 60:.1f} min, 1 torch thread): "
        f"slippery FrozenLake, {cfg.horizon}-step episodes; pi_eps = the value-iteration "
        f"expert with probability 1 - eps, uniform otherwise; {k:,} comparisons per "
        f"scenario, each of up to {cfg.budget} episode pairs (each side its own episodes), "
        f"alpha = {cfg.alpha}. Exact success: pi_{cfg.eps_a} {null['exact'][0]:.4f} "
        f"(played: {null['estimated'][0]:.4f}), pi_{cfg.eps_b} {alt['exact'][1]:.4f} "
        f"(played: {alt['estimated'][1]:.4f}); null: pi_{cfg.eps_a} vs itself, alternative: "
        f"pi_{cfg.eps_a} vs pi_{cfg.eps_b}, exact difference {alt['truth']:+.4f}.\n\n"
        + _report.table(["", "fixed: paired t", "sequential: betting CS"], rows)
        + f"\n\nThe fixed test's power by pairs: {curve}.\n"
        + f"\n![power and calibration](results/{NAME}.png)\n",
    )


def main(argv: list[str] | None = None) -> dict:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    mdp, q = lake()
    t0 = time.perf_counter()
    null = scenario(mdp, q, cfg.eps_a, cfg, seed=1)
    alt = scenario(mdp, q, cfg.eps_b, cfg, seed=2)
    wall = time.perf_counter() - t0
    summ = summary(null, alt, cfg)
    figure(null, alt, summ, cfg, _report.results_dir(out_dir) / f"{NAME}.png")
    md = markdown(cfg, null, alt, summ, wall)
    print(md)
    payload = {"config": asdict(cfg), "null": null, "alternative": alt, "summary": summ,
               "wall_seconds": wall}  # fmt: skip
    print("results:", _report.write(NAME, _keys_as_strings(payload), md, out_dir=out_dir))
    return payload


def _keys_as_strings(value):
    if isinstance(value, dict):
        return {str(k): _keys_as_strings(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_keys_as_strings(v) for v in value]
    return value


if __name__ == "__main__":
    main()

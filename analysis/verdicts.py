"""Claims of the paper checked against our measurements: each claim of a figure file gets a verdict.

A claim is one table of a figure file's ``[[figure.claims]]``; its keys say what kind it is:

* ``better = G``, ``than = H``: group G's final greedy return is above H's. Welch's one-sided t-test over seeds:
  *reproduced* at p < 0.05, *not shown* when G's mean is higher but not significantly, *not reproduced* when it
  is not higher (the difference goes the other way).
* ``group = G``, ``above_reference = R``: G's final return is above reference policy R's (one-sample t-test of
  the seeds' returns against R's mean, the same verdicts).
* ``group = G``, ``paper = x``: the paper's number beside ours; with ``comparable = false`` (another reward scale)
  the verdict is *not comparable*, else *reproduced* when x lies in our 95 % CI, *not reproduced* outside it.
* ``exponent = ALGO``, ``between = [lo, hi]``: the exponent k of inference time ∝ N^k is in [lo, hi]: *reproduced*
  when k's whole 95 % CI lies inside, *not reproduced* when it lies wholly outside, *not shown* otherwise — so a
  fit of k = 1.51 ± 0.3 does not pass for "quadratic".
* ``recovers = G``, ``own = H``, ``told = T``: the fraction of the told learner's gain over its own twin that G
  recovers, (G − H) / (T − H) of the groups' mean final returns, with a percentile-bootstrap 95 % CI (each group's
  seeds resampled alone). A number stated, not a test of the paper (*not comparable*); ``goal = x`` says whether
  the CI lies above x.
* ``metric = KEY`` (an analysis figure, Table 1) with ``above = "shuffled"`` (the figure beats its shuffled-pairs
  baseline), ``above = 0``, ``below = OTHER_KEY`` (e.g. the return with noise below the return with messages) or
  ``above_group = H`` (above the same figure of analysed group H, e.g. a channel-cut twin; Welch): one-sided
  t-tests over the analysed checkpoints, of the figure's first analysed group or of ``group = G``.

A figure tests several claims at once, so ``judge_figure`` holds its family-wise error at 5 %: a tested claim is
*reproduced* only when its p-value stays below 0.05 after Holm's step-down correction over the figure's tested
claims (a claim significant alone but not after it is *not shown*).

The figure's verdict, strict as a referee reads it: *not reproduced* when its headline claim (``headline = true``,
else its first) goes the other way, or every claim does; *reproduced* when every claim is; *partly* only
when some claims hold significantly and others do not; *not shown* when no claim holds significantly and the
headline does not go the other way.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from convoy.stats import ci95_half

REPRODUCED, PARTLY, NOT_SHOWN, NOT = "reproduced", "partly", "not shown", "not reproduced"
NOT_COMPARABLE = "not comparable"
ALPHA = 0.05


@dataclass
class Verdict:
    claim: str
    paper: str
    ours: str
    verdict: str
    why: str = ""
    p: float | None = None  # the one-sided test's p-value, for claims decided by one
    headline: bool = False  # the figure's main claim: if it goes the other way, so does the figure


def mean_ci(values: list[float]) -> str:
    """``41.2 ± 3.1 (n=5)``."""
    if not values:
        return "–"
    x = np.asarray(values, dtype=np.float64)
    return f"{x.mean():.3g} ± {ci95_half(x, single=0.0):.2g} (n={len(x)})"


def _finals(groups: dict[str, dict[str, Any]], name: str) -> list[float]:
    group = groups.get(name)
    if group is None:
        raise KeyError(f"no group {name!r}; the sweep's groups: {', '.join(groups)}")
    return [float(v) for v in group["final"]["values"]]


def p_above(a: list[float], b: list[float] | float) -> tuple[float, float]:
    """(difference of means, p-value) of ``mean(a) > mean(b)`` (Welch; one-sample against a number)."""
    with warnings.catch_warnings():  # nearly equal values: scipy warns of precision loss, the p-value stands
        warnings.simplefilter("ignore", RuntimeWarning)
        return _t_test(a, b)


def _t_test(a: list[float], b: list[float] | float) -> tuple[float, float]:
    x = np.asarray(a, dtype=np.float64)
    if isinstance(b, float | int):
        diff = float(x.mean() - b)
        if not _testable(x):
            return diff, 0.0 if diff > 0 else 1.0
        return diff, float(stats.ttest_1samp(x, b, alternative="greater").pvalue)
    y = np.asarray(b, dtype=np.float64)
    diff = float(x.mean() - y.mean())
    if not _testable(x, y):
        return diff, 0.0 if diff > 0 else 1.0
    return diff, float(stats.ttest_ind(x, y, equal_var=False, alternative="greater").pvalue)


def _testable(*samples: np.ndarray) -> bool:
    """Whether a t-test can speak: every sample has two values or more and some sample varies."""
    return min(len(v) for v in samples) >= 2 and any(v.std(ddof=1) > 0 for v in samples)


def difference_text(a: list[float], b: list[float] | None = None, word: str = "difference") -> str:
    """``difference +12.3 [4.1, 20.5]``: mean(a) − mean(b) with its two-sided 95 % t-interval (Welch), or with
    ``b`` None the mean of paired differences ``a`` with theirs; no interval from one seed or no spread."""
    x = np.asarray(a, dtype=np.float64)
    y = None if b is None else np.asarray(b, dtype=np.float64)
    diff = float(x.mean() - (0.0 if y is None else y.mean()))
    if not _testable(*([x] if y is None else [x, y])):
        return f"{word} {diff:+.3g} (no CI: one seed or no spread)"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        test = stats.ttest_1samp(x, 0.0) if y is None else stats.ttest_ind(x, y, equal_var=False)
        ci = test.confidence_interval(0.95)
    return f"{word} {diff:+.3g} [{ci.low:.3g}, {ci.high:.3g}]"


def significant(diff: float, p: float) -> bool:
    """Whether a one-sided test's (difference, p-value) says "above" at ``ALPHA``."""
    return diff > 0 and p < ALPHA


def _tested(text: str, paper: str, ours: str, diff: float, p: float) -> Verdict:
    if significant(diff, p):
        return Verdict(text, paper, ours, REPRODUCED, f"p = {p:.3g} (one-sided t-test)", p)
    if diff > 0:
        return Verdict(text, paper, ours, NOT_SHOWN, f"higher but not significantly: p = {p:.2g}", p)
    return Verdict(text, paper, ours, NOT, f"lower: difference {diff:.3g}, p = {p:.2g}", p)


def holm(verdicts: list[Verdict]) -> list[Verdict]:
    """Holm's correction over the tested claims: each *reproduced* one keeps its verdict only if its adjusted
    p-value is below ``ALPHA``; the others are unchanged."""
    tested = sorted(((v.p, v) for v in verdicts if v.p is not None), key=lambda pv: pv[0])
    m, running = len(tested), 0.0
    for rank, (p, v) in enumerate(tested):
        running = max(running, min(1.0, (m - rank) * p))
        if v.verdict != REPRODUCED or m == 1:
            continue
        if running < ALPHA:
            v.why = f"p = {v.p:.3g}, {running:.3g} after Holm's correction over {m} tests"
        else:
            v.verdict, v.why = NOT_SHOWN, f"p = {v.p:.3g} alone, {running:.2g} after Holm's correction over {m} tests"
    return verdicts


def judged_returns(
    groups: list[dict[str, Any]], extra: dict[str, Any]
) -> tuple[list[dict[str, Any]], dict[str, Any], str]:
    """The returns a figure's claims are judged on, and which: where every run of every group was re-scored on the
    held-out episodes, its last policy's held-out return (the same policy as its final evaluation's, on more
    episodes that nothing was chosen on) and the references on those very episodes; else each run's final greedy
    evaluation."""
    lasts = [((g.get("held_out") or {}).get("last") or {}).get("values") or [] for g in groups]
    if not any(lasts) or any(len(v) != len(g["final"]["values"]) for v, g in zip(lasts, groups, strict=True)):
        return groups, extra, "final"
    held = [{**g, "final": {**g["final"], "values": v}} for g, v in zip(groups, lasts, strict=True)]
    refs = extra.get("held_out_references") or extra.get("references") or {}
    return held, {**extra, "references": refs}, "held_out"


def metric_values(analyses: list[dict[str, Any]]) -> tuple[dict[str, dict[str, list[Any]]], dict[str, str]]:
    """Each analysis figure's values and shuffled baselines over runs (``analyses``: one stored analysis a run, as
    Table 1's recording writes it), keyed as ``metric`` claims name them, and each key's readable name."""
    figures: dict[str, dict[str, list[Any]]] = {}
    names: dict[str, str] = {}
    for analysis in analyses:
        for f in analysis["figures"]:
            names[f["key"]] = f["name"]
            entry = figures.setdefault(f["key"], {"value": [], "shuffled": []})
            entry["value"].append(f["value"])
            entry["shuffled"].append(f["shuffled"])
    return figures, names


def judge_figure(
    claims: list[dict[str, Any]], groups: dict[str, dict[str, Any]], extra: dict[str, Any]
) -> list[Verdict]:
    """Every claim of a figure, Holm-corrected together; the first is the headline unless one says it is."""
    verdicts = holm([judge(c, groups, extra) for c in claims])
    flagged = [v for v, c in zip(verdicts, claims, strict=True) if c.get("headline")]
    for v in flagged or verdicts[:1]:
        v.headline = True
    return verdicts


def judge(claim: dict[str, Any], groups: dict[str, dict[str, Any]], extra: dict[str, Any]) -> Verdict:
    """One claim's verdict from the summary's ``groups`` (by name) and ``extra`` (references, exponents, analysis
    figures by key: lists of values over seeds)."""
    text, paper = str(claim["text"]), str(claim.get("paper_says", claim.get("paper", "")))
    try:
        if "better" in claim:
            a, b = _finals(groups, claim["better"]), _finals(groups, claim["than"])
            if not a or not b:
                return Verdict(text, paper, "no final returns yet", NOT, "a group has no completed job")
            return _tested(text, paper, f"{mean_ci(a)} vs {mean_ci(b)}; {difference_text(a, b)}", *p_above(a, b))
        if "above_reference" in claim:
            a = _finals(groups, claim["group"])
            ref = extra.get("references", {}).get(claim["above_reference"])
            if ref is None:  # the env's references were measured without it (other rules): no evidence either way
                known = ", ".join(extra.get("references", {})) or "none"
                return Verdict(text, paper, "not measured", NOT_SHOWN,
                               f"no reference {claim['above_reference']!r} (measured: {known})")  # fmt: skip
            if not a:
                return Verdict(text, paper, "no final returns yet", NOT, "a group has no completed job")
            ours = f"{mean_ci(a)} vs {claim['above_reference']} {ref:.3g}"
            return _tested(text, paper, ours, *p_above(a, float(ref)))
        if "group" in claim and "paper" in claim:
            a = _finals(groups, claim["group"])
            ours = mean_ci(a)
            if not claim.get("comparable", True):
                return Verdict(text, paper, ours, NOT_COMPARABLE, str(claim.get("why", "another reward scale")))
            x = np.asarray(a, dtype=np.float64)
            gap, ci = abs(float(x.mean()) - float(claim["paper"])), ci95_half(x, single=0.0)
            verdict = REPRODUCED if gap <= ci else NOT
            return Verdict(text, paper, ours, verdict, f"|ours − paper| = {gap:.3g}, CI {ci:.2g}")
        if "exponent" in claim:
            return _judge_exponent(claim, text, paper, extra.get("exponents", {}).get(claim["exponent"]))
        if "recovers" in claim:
            own, told = _finals(groups, claim["own"]), _finals(groups, claim["told"])
            return _judge_recovered(claim, text, paper, _finals(groups, claim["recovers"]), own, told)
        if "metric" in claim:
            by_group = extra.get("analysis_groups") or {}
            figures = by_group[claim["group"]] if "group" in claim else extra.get("analysis", {})
            if "above_group" in claim:
                return _judge_across(claim, text, paper, figures, by_group.get(claim["above_group"], {}))
            return _judge_metric(claim, text, paper, figures)
    except KeyError as exc:  # a group the stored figure does not have (e.g. a control added since): not measured
        return Verdict(text, paper, "not measured", NOT_SHOWN, f"{exc.args[0]}: run the figure again")
    raise ValueError(f"claim {text!r}: no kind recognised (better/than, above_reference, paper, exponent, metric)")


def recovered(
    gain: list[float], own: list[float], told: list[float], resamples: int = 2000
) -> tuple[float, float, float]:
    """(G − H) / (T − H) of the mean final returns of G = ``gain``, H = ``own``, T = ``told`` and its
    percentile-bootstrap 95 % CI, each group's seeds resampled alone (fixed seed: a page regenerated reads the
    same); NaN where the told learner's resampled mean is not above its twin's (there is no gain to recover)."""
    rng = np.random.default_rng(0)
    g, h, t = (np.asarray(v, dtype=np.float64) for v in (gain, own, told))

    def ratio(gm: np.ndarray, hm: np.ndarray, tm: np.ndarray) -> np.ndarray:
        span = tm - hm
        return np.where(span > 0, (gm - hm) / np.where(span > 0, span, 1.0), np.nan)

    point = float(ratio(g.mean(), h.mean(), t.mean()))
    means = [rng.choice(x, size=(resamples, len(x))).mean(axis=1) for x in (g, h, t)]
    boot = ratio(*means)
    if np.isnan(boot).mean() > 0.025:  # the gain itself is not sure: no interval
        return point, math.nan, math.nan
    lo, hi = np.nanpercentile(boot, [2.5, 97.5])
    return point, float(lo), float(hi)


def _judge_recovered(
    claim: dict[str, Any], text: str, paper: str, gain: list[float], own: list[float], told: list[float]
) -> Verdict:
    if not (gain and own and told):
        return Verdict(text, paper, "no final returns yet", NOT_SHOWN, "a group has no completed job")
    point, lo, hi = recovered(gain, own, told)
    if math.isnan(point):
        return Verdict(text, paper, "no gain to recover", NOT_COMPARABLE, "the told learner is not above its twin")
    ours = f"{point:.0%} [{lo:.0%}, {hi:.0%}]" if math.isfinite(lo) else f"{point:.0%} (no CI: the told gain is unsure)"
    goal = claim.get("goal")
    why = "a fraction stated, not a claim of the paper"
    if goal is not None:
        met = "met" if math.isfinite(lo) and lo > float(goal) else "not met"
        why += f"; goal ≥ {float(goal):.0%}: {met}"
    return Verdict(text, paper, ours, NOT_COMPARABLE, why)


def _judge_across(
    claim: dict[str, Any], text: str, paper: str, figures: dict[str, Any], other: dict[str, Any]
) -> Verdict:
    key = claim["metric"]
    a, b = (f.get(key, {}).get("value") or [] for f in (figures, other))
    a, b = [v for v in a if v is not None], [v for v in b if v is not None]
    if not a or not b:
        return Verdict(text, paper, "not measured", NOT_SHOWN, f"{key!r} of a group is missing: run the figure again")
    return _tested(text, paper, f"{mean_ci(a)} vs {mean_ci(b)}; {difference_text(a, b)}", *p_above(a, b))


def _judge_exponent(claim: dict[str, Any], text: str, paper: str, fit: Any) -> Verdict:
    """``fit``: ``{"k": k, "ci": [lo, hi]}`` (a k without a CI, from an older record or too few rounds, shows
    nothing)."""
    lo, hi = (float(v) for v in claim["between"])
    expected = f"expected {lo:g} ≤ k ≤ {hi:g}"
    if isinstance(fit, dict) and fit.get("ci") is not None and math.isfinite(fit["k"]):
        k, (k_lo, k_hi) = float(fit["k"]), (float(v) for v in fit["ci"])
        ours = f"k = {k:.2f} [{k_lo:.2f}, {k_hi:.2f}]"
        if lo <= k_lo and k_hi <= hi:
            return Verdict(text, paper, ours, REPRODUCED, f"{expected}: the 95 % CI lies inside")
        if k_hi < lo or k_lo > hi:
            return Verdict(text, paper, ours, NOT, f"{expected}: the 95 % CI lies outside")
        return Verdict(text, paper, ours, NOT_SHOWN, f"{expected}: the 95 % CI reaches outside")
    if isinstance(fit, dict):
        fit = fit.get("k")  # too few rounds for a CI
    if isinstance(fit, float | int) and math.isfinite(fit):
        why = f"{expected}; no CI: run the figure again with --repeats ≥ 2"
        return Verdict(text, paper, f"k = {fit:.2f}", NOT_SHOWN, why)
    return Verdict(text, paper, "not measured", NOT_SHOWN, "no timing for this algorithm")


def _judge_metric(claim: dict[str, Any], text: str, paper: str, figures: dict[str, dict[str, list[float]]]) -> Verdict:
    key = claim["metric"]
    measured = key in figures and figures[key]["value"]
    if "above" not in claim and "below" not in claim:  # a number shown, not a claim tested
        ours = mean_ci(figures[key]["value"]) if measured else "not measured"
        return Verdict(text, paper, ours, NOT_COMPARABLE, str(claim.get("why", "a number only")))
    if not measured:
        return Verdict(text, paper, "not measured", NOT_SHOWN, f"no analysis figure {key!r}: run the figure again")
    values = figures[key]["value"]
    ours = mean_ci(values)
    above, below = claim.get("above"), claim.get("below")
    if above == "shuffled":
        base = [v for v in figures[key].get("shuffled", []) if v is not None]
        if not base:
            return Verdict(text, paper, ours, NOT_SHOWN, "no shuffled baseline: run the figure again")
        diff = [v - s for v, s in zip(values, base, strict=False)]
        ours = f"{ours}; shuffled {mean_ci(base)}; {difference_text(diff, word='paired gap')}"
        return _tested(text, paper, ours, *p_above(diff, 0.0))
    if above is not None:
        return _tested(text, paper, ours, *p_above(values, float(above)))
    other = figures.get(str(below), {}).get("value", [])
    diff = [o - v for v, o in zip(values, other, strict=False)]
    if not diff:
        return Verdict(text, paper, ours, NOT_SHOWN, f"no figure {below!r}: run the figure again")
    ours = f"{below} {mean_ci(other)} vs {key} {ours}; {difference_text(diff, word='paired gap')}"  # the gap's order
    return _tested(text, paper, ours, *p_above(diff, 0.0))


def figure_verdict(verdicts: list[Verdict]) -> str:
    """The figure's word from its claims' (see the module's docstring)."""
    judged = [v for v in verdicts if v.verdict != NOT_COMPARABLE]
    if not judged:
        return NOT_COMPARABLE
    words = [v.verdict for v in judged]
    if any(v.headline and v.verdict == NOT for v in judged) or all(w == NOT for w in words):
        return NOT
    if all(w == REPRODUCED for w in words):
        return REPRODUCED
    return PARTLY if REPRODUCED in words else NOT_SHOWN

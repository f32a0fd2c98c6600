"""
The pre-registered claims of the pipeline study on the forgetting screen's setting (README beside this file): read by
``python -m sb3_lifelong.experiments report`` and :func:`sb3_lifelong.experiments.claims.load_claims`.

Each claim is one per-seed series (a paired difference or a per-seed ratio), so the interval the report gives beside
it is the paired 95 % interval of its mean. The engine's verdict is the criterion on the mean; the README's reading
(:func:`reading`) adds the interval: *holds* when the whole interval is on the claimed side of the threshold, *fails*
when the whole interval is on the other side, *inconclusive* when it contains the threshold.
"""

import math

from sb3_lifelong.experiments.claims import Claim, ratio

#: each claim's threshold and claimed side (True: above it), for the README's reading
THRESHOLDS: dict[str, tuple[float, bool]] = {
    "C1 MPO forgets Env-A": (0.8, False),
    "C2 online CRR remembers Env-A better than MPO": (0.0, True),
    "C3a the student is at least MPO's end agent in Env-A": (0.9, True),
    "C3b the student is close to MPO's end agent in Env-B": (0.9, True),
}


def difference(first: dict[int, float], second: dict[int, float]) -> dict[int, float]:
    """:return: seed -> first - second, on the seeds both have"""
    return {s: first[s] - second[s] for s in first if s in second}


def reading(claim: str, low: float, high: float, verdict: str = "") -> str:
    """
    The README's reading of a claim from the 95 % interval of its series' mean.

    :param claim: the claim's name (a key of :data:`THRESHOLDS`)
    :param low: the interval's lower end
    :param high: the interval's upper end
    :param verdict: the engine's verdict: *not testable* and *no data* stand as they are
    :return: ``holds``, ``fails`` or ``inconclusive`` (or the verdict that stands)
    """
    if verdict in ("not testable", "no data"):
        return verdict
    if not (math.isfinite(low) and math.isfinite(high)):
        return "inconclusive"
    threshold, above = THRESHOLDS[claim]
    if (low > threshold) if above else (high < threshold):
        return "holds"
    if (high < threshold) if above else (low > threshold):
        return "fails"
    return "inconclusive"


CLAIMS: list[Claim] = [
    Claim(
        "C1 MPO forgets Env-A",
        "MPO's Env-A return at the end of Env-B (last 3 evaluations) over its Env-A return at the switch (last 2 "
        "evaluations of Stage 1: the frozen Stage-1 agent) is <= 0.8",
        lambda s: {"end / switch": ratio(s.score("MPO", "Env-A"), s.extra("MPO|switch|Env-A"))},
        lambda m: m["end / switch"] <= 0.8,
        needs=("env_a_learnt", "steady"),
    ),
    Claim(
        "C2 online CRR remembers Env-A better than MPO",
        "online CRR (exp, beta=1, continued from the Stage-1 agent) ends Env-B with a higher Env-A return than MPO "
        "(paired difference > 0)",
        lambda s: {"online CRR - MPO": difference(s.score("online CRR_exp_beta1", "Env-A"), s.score("MPO", "Env-A"))},
        lambda m: m["online CRR - MPO"] > 0,
        needs=("env_a_learnt", "steady"),
    ),
    Claim(
        "C3a the student is at least MPO's end agent in Env-A",
        "the distilled CRR exp beta=1 student (mean of its two student seeds) over MPO's end agent, in Env-A, is >= 0.9 "
        "(at least MPO's, within a 10 % non-inferiority margin)",
        lambda s: {"student / MPO (Env-A)": ratio(s.score("CRR_exp_beta1", "Env-A"), s.score("MPO", "Env-A"))},
        lambda m: m["student / MPO (Env-A)"] >= 0.9,
        needs=("env_a_learnt", "steady"),
    ),
    Claim(
        "C3b the student is close to MPO's end agent in Env-B",
        "the distilled CRR exp beta=1 student over MPO's end agent, in Env-B, is >= 0.9",
        lambda s: {"student / MPO (Env-B)": ratio(s.score("CRR_exp_beta1", "Env-B"), s.score("MPO", "Env-B"))},
        lambda m: m["student / MPO (Env-B)"] >= 0.9,
        needs=("env_a_learnt", "steady"),
    ),
]

"""
The pre-registered claims of this study, the paper's two-stage claims at CPU scale: read by ``python -m
sb3_lifelong.experiments report`` and by :func:`sb3_lifelong.experiments.claims.load_claims`. The criteria were
written before the study's runs (its README).
"""

import numpy as np

from sb3_lifelong.experiments.claims import Claim, mean_over_envs, ratio

#: the methods that need no task boundaries, compared by claim C3
LIFELONG_METHODS = ("MPO", "online CRR_indicator", "online CRR_exp_beta1", "CRR_exp_beta1", "CRR_indicator", "BC")

CLAIMS: list[Claim] = [
    Claim(
        "C1 forgetting",
        "MPO's Env-A return at the end of Stage 2 is <= 70 % of its Env-A return at the switch",
        lambda s: {"end / switch": ratio(s.score("MPO", "Env-A"), s.extra("MPO|switch|Env-A"))},
        lambda m: m["end / switch"] <= 0.7,
        needs=("env_a_learnt", "steady"),
    ),
    Claim(
        "C2a conservative online CRR remembers",
        "online CRR (exp, beta=1) ends with a higher Env-A return than MPO",
        lambda s: {"CRR beta=1": s.score("online CRR_exp_beta1", "Env-A"), "MPO": s.score("MPO", "Env-A")},
        lambda m: m["CRR beta=1"] > m["MPO"],
        needs=("env_a_learnt",),
    ),
    Claim(
        "C2b conservative online CRR learns Env-B slower",
        "online CRR (exp, beta=1)'s mean Env-B return over Stage 2 is below MPO's",
        lambda s: {
            "CRR beta=1": s.extra("online CRR_exp_beta1|stage2_area|Env-B"),
            "MPO": s.extra("MPO|stage2_area|Env-B"),
        },
        lambda m: m["CRR beta=1"] < m["MPO"],
    ),
    Claim(
        "C3 the pipeline is best",
        "the CRR exp beta=1 student has the best mean over Env-A and Env-B of the lifelong methods "
        + "("
        + ", ".join(LIFELONG_METHODS)
        + ")",
        lambda s: {m: mean_over_envs(s, m) for m in LIFELONG_METHODS},
        lambda m: all(m["CRR_exp_beta1"] >= v for k, v in m.items() if np.isfinite(v)),
        pairs=tuple(("CRR_exp_beta1", method) for method in LIFELONG_METHODS if method != "CRR_exp_beta1"),
    ),
    Claim(
        "C4a the imbalance drop",
        "the indicator student on Env-A + Env-B reaches <= 80 % of the Env-A-only indicator student in Env-A",
        lambda s: {"indicator / A-only": ratio(s.score("CRR_indicator", "Env-A"), s.score("CRR_indicator_A_only", "Env-A"))},
        lambda m: m["indicator / A-only"] <= 0.8,
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C4b beta=1 fixes it",
        "the exp beta=1 student on Env-A + Env-B reaches >= 90 % of the Env-A-only indicator student in Env-A",
        lambda s: {"exp beta=1 / A-only": ratio(s.score("CRR_exp_beta1", "Env-A"), s.score("CRR_indicator_A_only", "Env-A"))},
        lambda m: m["exp beta=1 / A-only"] >= 0.9,
        needs=("env_a_learnt", "value_gap", "conservative"),
    ),
    Claim(
        "C5a reward scale",
        "scaling Env-B's rewards by 0.5 raises the indicator student's Env-A return",
        lambda s: {"scaled": s.score("CRR_indicator_scale_rwd_B", "Env-A"), "baseline": s.score("CRR_indicator", "Env-A")},
        lambda m: m["scaled"] > m["baseline"],
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C5b two actors",
        "one actor per environment (shared critic) raises the indicator student's Env-A return",
        lambda s: {"two actors": s.score("CRR_indicator_two_actors", "Env-A"), "baseline": s.score("CRR_indicator", "Env-A")},
        lambda m: m["two actors"] > m["baseline"],
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C5c BC beats the indicator in Env-A",
        "behaviour cloning on Env-A + Env-B has a higher Env-A return than the indicator student",
        lambda s: {"BC": s.score("BC", "Env-A"), "indicator": s.score("CRR_indicator", "Env-A")},
        lambda m: m["BC"] > m["indicator"],
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C5d sampling ratio hurts the indicator",
        "the indicator student's Env-A return falls as Env-B's share grows: 1:1 > raw 1:5 > 1:10",
        lambda s: {
            "1:1": s.score("CRR_indicator_ratio_1to1", "Env-A"),
            "1:5": s.score("CRR_indicator", "Env-A"),
            "1:10": s.score("CRR_indicator_ratio_1to10", "Env-A"),
        },
        lambda m: m["1:1"] > m["1:5"] > m["1:10"],
        pairs=(("1:1", "1:5"), ("1:5", "1:10")),
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C5e beta=1 is robust to the ratio",
        "the exp beta=1 student's Env-A return at 1:10 is >= 90 % of its return at 1:1",
        lambda s: {
            "1:10 / 1:1": ratio(s.score("CRR_exp_beta1_ratio_1to10", "Env-A"), s.score("CRR_exp_beta1_ratio_1to1", "Env-A"))
        },
        lambda m: m["1:10 / 1:1"] >= 0.9,
        needs=("env_a_learnt", "value_gap"),
    ),
    Claim(
        "C6 overestimation on Env-A data",
        "the indicator student's average Q over Env-A data exceeds the Env-A-only student's",
        lambda s: {"indicator": s.extra("CRR_indicator|q|Env-A"), "A-only": s.extra("CRR_indicator_A_only|q|Env-A")},
        lambda m: m["indicator"] > m["A-only"],
    ),
]

"""
The pre-registered claims of this study, the paper's three-stage claims (its appendix): read by ``python -m
sb3_lifelong.experiments report`` and by :func:`sb3_lifelong.experiments.claims.load_claims`. The criteria were
written before the study's runs (its README).
"""

from sb3_lifelong.experiments.claims import Claim, mean_over, mean_over_envs, ratio

#: the claims of the three-stage set-up (Env-A, Env-B, Env-C; the paper's appendix), pre-registered in
#: benchmarks/studies/paper_cpu_three/README.md before any seed ran
CLAIMS: list[Claim] = [
    Claim(
        "T1a forgetting Env-A",
        "MPO's Env-A return at the end of Stage 3 is <= 70 % of its Env-A return at the end of Stage 1",
        lambda s: {"end / switch": ratio(s.score("MPO", "Env-A"), s.extra("MPO|switch|Env-A"))},
        lambda m: m["end / switch"] <= 0.7,
        needs=("env_a_learnt", "steady"),
    ),
    Claim(
        "T1b forgetting Env-B",
        "MPO's Env-B return at the end of Stage 3 is <= 70 % of its Env-B return at the end of Stage 2",
        lambda s: {"end / switch": ratio(s.score("MPO", "Env-B"), s.extra("MPO|switch|Env-B"))},
        lambda m: m["end / switch"] <= 0.7,
        needs=("steady_b",),
    ),
    Claim(
        "T2a distillation recovers the earlier environments",
        "the CRR exp beta=1 student's mean return over Env-A and Env-B is above MPO's final one",
        lambda s: {
            "exp beta=1": mean_over(s, "CRR_exp_beta1", ("Env-A", "Env-B")),
            "MPO": mean_over(s, "MPO", ("Env-A", "Env-B")),
        },
        lambda m: m["exp beta=1"] > m["MPO"],
    ),
    Claim(
        "T2b distillation keeps the last environment",
        "the CRR exp beta=1 student's Env-C return is >= 80 % of MPO's final Env-C return",
        lambda s: {"student / MPO": ratio(s.score("CRR_exp_beta1", "Env-C"), s.score("MPO", "Env-C"))},
        lambda m: m["student / MPO"] >= 0.8,
    ),
    Claim(
        "T3a the imbalance drop",
        "the indicator student's Env-A return is <= 80 % of the exp beta=1 student's",
        lambda s: {"indicator / exp beta=1": ratio(s.score("CRR_indicator", "Env-A"), s.score("CRR_exp_beta1", "Env-A"))},
        lambda m: m["indicator / exp beta=1"] <= 0.8,
        needs=("env_a_learnt", "value_gap", "conservative"),
    ),
    Claim(
        "T3b exp beta=1 is the more reliable student",
        "the exp beta=1 student's mean return over the three environments is >= the indicator student's",
        lambda s: {"exp beta=1": mean_over_envs(s, "CRR_exp_beta1"), "indicator": mean_over_envs(s, "CRR_indicator")},
        lambda m: m["exp beta=1"] >= m["indicator"],
        needs=("conservative",),
    ),
]

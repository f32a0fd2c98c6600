"""
The pre-registered claims of this study: those of ``paper_cpu_three`` (its README says so), read from that study's folder.
"""

import pathlib

from sb3_lifelong.experiments.claims import load_claims

CLAIMS = load_claims(pathlib.Path(__file__).resolve().parent.parent / "paper_cpu_three" / "claims.py")

"""Everything that speaks the authors' formats.

Their checkpoint keys (`convert`) and their model-level forward conventions
(`model_forward`), for loading the released weights and for equivalence checks against the
official TAPTR code (v1, v2 and v3). Their TAP-Vid evaluation recipe is a protocol of the
evaluation (`taptr.eval.official_protocol`).
"""

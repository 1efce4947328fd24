"""Everything that speaks the authors' formats.

Their checkpoint keys (`convert`), their model-level forward conventions (`forward`) and
their TAP-Vid evaluation recipe (`evaluation`), for equivalence checks against the
official TAPTRv2 code.
"""

"""The paper's baselines (SPEC section 5, Table 1): straight-ray volume models and the named
methods that run them beside clrefract's own fits (clrefract.baselines.methods)."""

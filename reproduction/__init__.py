"""The paper reproduction: an application of qpctl (``make demo``), beside ``benchmarks/``.

    python -m reproduction --out results/paper

runs the paper's scenario under every law, the v_ref sweep and the claims' verdicts
(:mod:`reproduction.reproduce`).
"""

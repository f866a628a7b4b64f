"""The paper's studies, reproducible from a scene file: the protocol optimisation (Fig. 2)."""

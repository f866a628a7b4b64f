"""Design studies: what a sensor design can measure. The derivatives of a press's measurements
through the coupled model (:mod:`.sensitivity`), the Fisher information and Cramér–Rao bounds
they give (:mod:`.bounds`), and the study over designs, positions, depths and sizes (:mod:`.study`)."""

"""The paper's methods as published: PSO and PSO+ (Eq. 12-16) and RLS (Eq. 17) on one step.

``protocol`` (the Section 5.1 cut: filter, resample, 200 points to identify and 400 to test),
``pso`` (the swarm) with ``batchfilter`` (one input through every particle's filter at once),
``rls``, ``identify`` (``identify_paper_method``: the methods on a recording, with the covariance
and identifiability of what one step carries) and ``plots`` (the figures of ``station paper``).
"""

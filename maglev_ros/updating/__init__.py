"""Hierarchical model updating of the twin (paper 000, Secs. 4-5): guideway layer (E, rho, kb from
measured frequencies + MAC [+ static deflection]) then magnetic-force layer (kp, kv, ka from the
measured electromagnet acceleration), with an Elman-network surrogate trained on optimal Latin
hypercube samples, MOPSO with a grid archive, and grey relational projection (GRP) to pick one
Pareto solution. Identifiability (ridges such as the common scale of E and rho) is detected from the
SVD of the whitened sensitivity matrix and reported as identifiable combinations.

No rclpy here; torch is imported lazily (only in ``surrogate.py``).
"""

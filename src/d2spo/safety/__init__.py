"""Data-driven CBF machinery of D²SPO (Sec. IV-A, IV-B, IV-D): nominal model, datasets, h_Θ, π_Ω.

The sensor enters only through `features_fn(pose, context) -> x [K]`, a pure function that is
differentiable in the pose (x, y, θ); the environment's lidar is wired in by the algorithm. See
docs/cbf.md for the design. Import the modules themselves (`d2spo.safety.cbf`, `.datasets`,
`.joint_policy`, `.nominal`, `.filter`, `.bounds`, `.certify`).
"""

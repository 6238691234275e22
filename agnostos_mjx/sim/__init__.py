"""The simulated world below the runtime: the scene (world), the arm's control, success
conditions, named observables, per-world colours, keyframes, rigid-body maths, RLBench's
colours, the scene as text, and the action type (actions, which imports neither JAX nor
MuJoCo: this package's face imports nothing)."""

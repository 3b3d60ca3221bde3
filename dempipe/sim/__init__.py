"""The simulation: Model, State, Control, the formulas, contact laws, kernels for two targets."""

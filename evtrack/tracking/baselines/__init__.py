"""The paper's baselines as motion sources: frame-to-frame RGB flow and the generative event
model."""

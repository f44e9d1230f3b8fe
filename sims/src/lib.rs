//! The simulated texel camera: scenes, ray casting, effects, trajectories and ground truth.

"""Learned downwash models: features, models, labels, data sets, training, checkpoints.

Modules (import them directly; this package imports nothing heavy on its own):

- `downwash.features`: the model inputs (paper eq. 4, NED mapping), NumPy and torch
- `downwash.models`: `EquivariantModel`, `GeneralEquivariantModel`, `ShallowMLP`, `DeepSNMLP`, `MODEL_KINDS`
- `downwash.labels`: labels ``f = a - u`` from flight logs, the label-noise floor
- `downwash.datasets`: `Dataset`, `load_dataset`, `split_by_flight`, `shorten_per_stage`
- `downwash.train`: `TrainConfig`, `train_model`, `rmse`
- `downwash.ensemble`: `train_ensemble`, many models of one kind as one batched network
- `downwash.checkpoint`: `save_checkpoint`, `load_checkpoint` (no code runs on load)
- `downwash.predictor`: `LearnedPredictor`, a model in the control loop (`sim.predictor.Predictor`)
- `downwash.fused`: the predictor's compiled one-pass kernel
- `downwash.conditions`: the tracking conditions and what each flies with
- `downwash.staged`: the staged collection pipeline, provenance and `ensure_models`
- `downwash.manifest`: a staged collection's record of every log, checked before training
- `downwash.swarm_data`: every vehicle's labels with its padded neighbour set (`SwarmDataset`)
- `downwash.swarm_models`: models for many vehicles (`SWARM_MODEL_KINDS`), their checkpoints, `SwarmPredictor`
- `downwash.swarm_fused`: the compiled form of every model of sets (the swarm predictor's default backend)
- `downwash.swarm_train`: `train_swarm_model`
- `downwash.swarm_collection`: the swarm stages and the models of sets trained on them
- `downwash.sweep`: cached, resumable sweeps on Ray, bootstrap intervals, the paired claim

Data flows one way: `downwash` may import `sim`, never `experiments`.
"""

__all__ = [
    "features", "models", "labels", "datasets", "train", "ensemble", "checkpoint", "predictor", "fused",
    "conditions", "staged", "swarm_data", "swarm_models", "swarm_train", "swarm_collection", "sweep",
]

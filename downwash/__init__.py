"""Learned downwash models: features, models, labels, data sets, training, checkpoints.

Modules (import them directly; this package imports nothing heavy on its own):

- `downwash.features`: the model inputs (paper eq. 4, NED mapping), NumPy and torch
- `downwash.labels`: labels ``f = a - u`` from flight logs, every target with its neighbour set, the label-noise floor
- `downwash.datasets`: the one data set (`Dataset`, a neighbour axis; the pair is its K = 1 case), `load_dataset`, splits
- `downwash.models`: the per-neighbour models (`EquivariantModel`, `GeneralEquivariantModel`, `ShallowMLP`, `DeepSNMLP`)
- `downwash.set_models`: the models of sets (summed per-neighbour models, equivariant and plain deep sets)
- `downwash.registry`: the one registry of model kinds (`MODEL_KINDS`, `make_model`)
- `downwash.train`: `TrainConfig`, `train_model` for every kind, `rmse`, `save_trained`
- `downwash.ensemble`: `train_ensemble`, many per-neighbour models of one kind as one batched network
- `downwash.ensemble_network`: the ensemble's batched network, every member's arithmetic its own
- `downwash.ensemble_settle`: the deep members' spectral norms settled after training, side by side
- `downwash.checkpoint`: `save_checkpoint`, `load_checkpoint`, `wrap_pairwise` (no code runs on load)
- `downwash.predictor`: `LearnedPredictor`, any model in the control loop (`sim.predictor.Predictor`)
- `downwash.fused`: the per-neighbour models' compiled pieces
- `downwash.set_fused`: the predictor's compiled pass for every kind (the default backend)
- `downwash.conditions`: the tracking conditions and what each flies with
- `downwash.staged`: the staged collection pipeline, provenance and `ensure_models`
- `downwash.manifest`: a staged collection's record of every log, checked before training
- `downwash.swarm_collection`: the many-vehicle stages and the models of sets trained on them
- `downwash.sweep`: cached, resumable sweeps on Ray (`run_sweep`)
- `downwash.sweep_cells`: a sweep's grid, its cells, their training in batches and their cache
- `downwash.sweep_stats`: a sweep's bootstrap intervals and the paired claim
- `downwash.sweep_report`: a sweep's tables and figure

Data flows one way: `downwash` may import `sim`, never `experiments`.
"""

__all__ = [
    "features", "labels", "datasets", "models", "set_models", "registry", "train", "ensemble", "ensemble_network",
    "ensemble_settle", "checkpoint", "predictor", "fused", "set_fused", "conditions", "staged", "manifest",
    "swarm_collection", "sweep", "sweep_cells", "sweep_stats", "sweep_report",
]

"""Learning: the DexRepNet policy, behaviour cloning, DAPG and parallel rollout samplers.

Modules: env_protocol (Env interface), policy (network + checkpoints), demo_dataset (.npz
demos), bc (behaviour cloning), trajectory, samplers (sequential / process / Ray), gae,
baseline (value MLP), npg (Fisher products, CG, natural step), dapg (the training loop),
curves (CSV + PNG learning curves).
"""

"""The building blocks the heads are made of: DiffusionNet's operators (`operators`) and network
(`diffusion_net`), functional-map solvers and point-map conversions (`functional_maps`),
differentiable functional-map layers (`fmap_layers`) and losses (`fmap_losses`), and the
batching of their inputs (`fmap_inputs`).
"""

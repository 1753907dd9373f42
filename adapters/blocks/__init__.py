"""The building blocks the heads are made of: DiffusionNet's operators (`operators`) and network
(`diffusion_net`), functional-map solvers and point-map conversions (`functional_maps`), and
differentiable functional-map layers and losses (`fmap_layers`).
"""

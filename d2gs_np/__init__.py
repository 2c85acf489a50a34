"""d2gs_np: a CPU research implementation of D2GS (deblurring deformable 3D Gaussian splatting).

Layers, dependencies pointing one way: geometry -> render (and reference) -> scene ->
blur, trajectory -> losses -> optim -> train -> data, metrics, evaluate, report, cli.
"""
__version__ = "0.1.0"

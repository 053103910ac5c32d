"""Adapters for code written against other libraries: their names, shapes and layouts,
computed by dego's core. ``dego.compat.gsplat`` (gsplat's ``rasterization``),
``dego.compat.dego`` (the official DeGO code's render layout and post-processing),
``dego.compat.gaussianflowocc`` (GaussianFlowOcc's temporal module) and
``dego.compat.gaussianformer`` (GaussianFormer's voxel aggregation heads)."""

"""Adapters for code written against other libraries: their names, shapes and layouts,
computed by dego's core. ``dego.compat.gsplat`` (gsplat's ``rasterization``),
``dego.compat.dego`` (the official DeGO code's render layout and post-processing),
``dego.compat.gaussianflowocc`` (GaussianFlowOcc's temporal module),
``dego.compat.gaussianformer`` (GaussianFormer's voxel aggregation heads) and
``dego.compat.torchmetrics`` (the metrics as ``torchmetrics.Metric``; needs the
``torchmetrics`` extra)."""

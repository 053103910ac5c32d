"""Adapters for code written against other libraries: their names, shapes and layouts,
computed by dego's core (``dego.compat.gsplat``)."""

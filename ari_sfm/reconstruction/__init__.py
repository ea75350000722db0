"""Reconstruction through the window: points, frames, their metrics and their error against a reference.

- ``triangulate``: points from pixels through the window (exact or ari rays);
- ``points``: the reconstructed points as records (points.json);
- ``reconstruct``: the reconstruction frames of a dataset (:func:`~ari_sfm.reconstruction.reconstruct.reconstruct`);
- ``metrics``: flatness, distances and the other reconstruction metrics (metrics.json);
- ``reference``: the error against a mesh or a cloud (Open3D).
"""

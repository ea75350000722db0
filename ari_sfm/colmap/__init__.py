"""COLMAP behind a flat window, in one place: the one pycolmap adapter (:mod:`.adapter`: models in and
out, COLMAP's own bundle adjustment and SfM), ``ari-sfm sfm`` (:mod:`.sfm`: COLMAP's SfM in a child
process, then refine-colmap), refine-colmap (:mod:`.refine`: the exact refractive refinement of a COLMAP
reconstruction) and the refractive COLMAP fork's FLATPORT cameras (:mod:`.fork`)."""

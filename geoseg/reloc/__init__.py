"""Relocalisation against a georeferenced image base (thesis §5.1): where was a query image taken?

* :mod:`~geoseg.reloc.retrieval`: the two steps on arrays, retrieval of the nearest base images
  (:class:`~geoseg.reloc.retrieval.RetrievalIndex`) and the query's absolute position from the
  relative-pose rays of its matches.
* :mod:`~geoseg.reloc.image_base`: an image base on disk (images, ``poses.csv``, ``camera.json``,
  cached embeddings); :mod:`~geoseg.reloc.base_build` writes one from geotagged images.
* :mod:`~geoseg.reloc.route_filter`: retrieval along a drive (a route-constrained filter over
  consecutive queries) instead of image by image.
* :mod:`~geoseg.reloc.essential_baseline`: the classical two-view baseline (features and an
  essential matrix) the learned relative pose is compared with.
* :mod:`~geoseg.reloc.base_structure`: the base's points, triangulated from neighbouring base
  images with their known poses, and a query's pose by PnP on them (metric where the rays of
  the relative poses are near-parallel).
* :mod:`~geoseg.reloc.networks`: the networks on images: the trunk and heads loaded, the
  embedding (eq. 5.1) and the relative poses of the relative-pose head (eq. 5.2).
* :mod:`~geoseg.reloc.localizer`: the library entry, :class:`~geoseg.reloc.localizer.Localizer`,
  chaining these for a list of query images (what ``geoseg localize`` runs).

Imports run one way: image_base imports retrieval, base_build imports image_base, the localizer
imports them all (base_structure lazily), and nothing here imports the localizer.
"""

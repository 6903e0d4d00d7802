"""Building and editing maps: every step from reference images to a map folder.

The steps, in the order the data travels (one implementation of each, shared by the builders)::

    describe        build_images (images + CSV, a teach bag), build_descriptors (precomputed),
                    an engine (distributed: Ray) describing for build_images
    partition       assemble (maps.partition: country / K-means; balance: split large submaps)
    index           assemble (maps.indexes: one FAISS index per submap)
    local features  local_features (ReferenceExtractor, store_features)
    calibration     build_images.write_map_calibration (fusion, ``calibration.json``),
                    local_features.calibrate_map (``p_correct``, ``verification.json``)
    store           maps.store / maps.reference_map (format v2 files, manifest last)

* :mod:`.build_images`, :mod:`.build_descriptors`, :mod:`.assemble`, :mod:`.balance`,
  :mod:`.local_features`, :mod:`.image_sources` (reference images: a folder or a URI);
* :mod:`.edit` (``map add`` / ``map remove``): the same describe (the map's
  :class:`~.local_features.ReferenceExtractor`), partition (K-means for new submaps), index,
  local-feature and ``p_correct`` calibration steps on the submaps an edit changes; the
  fusion's ``calibration.json`` stays the build's.
* ``build-map --engine ray`` (:mod:`vlm_vpr_ros.distributed.build`) calls
  :func:`.build_images.build_map` with an engine that describes, partitions and indexes on
  Ray; the local features, the calibrations and the store are the same calls.
* :mod:`.build_descriptors` (precomputed descriptors) has no images: no local features, no
  calibrations.

This package sits above :mod:`vlm_vpr_ros.localization` (the calibrations run the query's
own fusion and verification) and below :mod:`vlm_vpr_ros.distributed`; :mod:`vlm_vpr_ros.maps`
(the format and its storage) imports none of them.
"""

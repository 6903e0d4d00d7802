"""Everything about a map: a folder with a versioned manifest.

The build's path, in the order the data travels::

    images + coordinates CSV   -> build_images       -> assemble (partition, balance, indexes)
    a teach bag (bags.teach)   -> build_images       -> assemble
    precomputed descriptors    -> build_descriptors  -> indexes, balance (out of core)
    every builder              -> store (format v2 files, manifest last) -> reference_map

* :mod:`.format`: the manifest, format constants, the checks made at load;
* :mod:`.reference_map`: :class:`~.reference_map.ReferenceMap` (``ReferenceMap.load``) and the
  map's query-time descriptor; :mod:`.submap`, :mod:`.store` (format v2, memory-mapped),
  :mod:`.v1` (format 1, read and upgraded);
* :mod:`.build_images`, :mod:`.build_descriptors`, :mod:`.assemble`, :mod:`.partition`,
  :mod:`.balance`, :mod:`.indexes`, :mod:`.sources` (descriptor shards, ``.npy``, Parquet);
* :mod:`.edit` (``map add`` / ``map remove``) with :mod:`.transaction` and :mod:`.map_images`.
"""

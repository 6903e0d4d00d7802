"""Everything about a map folder: a versioned manifest, its files and how they are read.

The format and its storage only; building and editing maps is :mod:`vlm_vpr_ros.mapping`
(this package imports nothing from ``mapping``, ``localization``, ``distributed`` or ``bags``).

* :mod:`.format`: the manifest, format constants, the checks made at load;
* :mod:`.reference_map`: :class:`~.reference_map.ReferenceMap` (``ReferenceMap.load``) and the
  map's query-time descriptor; :mod:`.submap`, :mod:`.store` (format v2, memory-mapped),
  :mod:`.v1` (format 1, read and upgraded), :mod:`.mapped` (memory-mapped arrays, ids,
  read-ahead), :mod:`.watch` (the change notice that spares the file guard's ``stat`` calls on
  a quiet map);
* :mod:`.partition` (country / K-means submaps, the query's submap choice), :mod:`.indexes`
  (FAISS index kinds), :mod:`.search`, :mod:`.features` (stored local features),
  :mod:`.documents` (optional JSON documents), :mod:`.sources` (descriptor shards, ``.npy``,
  Parquet);
* :mod:`.transaction` (the commit of an edit) and :mod:`.map_images` (stored images).
"""

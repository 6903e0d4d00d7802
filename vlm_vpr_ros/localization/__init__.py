"""The query's path: image → descriptor → (prior) → retrieval → fusion → verification → answer.

* :mod:`.pipeline`: :class:`~.pipeline.LocalizationPipeline` = a map's descriptor + the localizer
  + the verifier
  (``LocalizationPipeline.open(map_dir).localize_image(rgb, prior_result)``);
* :mod:`.localizer`: submap choice, retrieval, fusion (:mod:`.fusion`);
* :mod:`.verification`: local features, geometry, ``p_correct``, the status rule;
* :mod:`.batch` and :mod:`.query_descriptors`: many queries from files (``vlm-vpr localize``).
"""

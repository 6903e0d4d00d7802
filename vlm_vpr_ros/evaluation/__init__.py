"""Scoring and showing results: metrics and tables (:mod:`.metrics`), the paper's ablation
(:mod:`.ablation`), plots (:mod:`.plots`) and the demo (:mod:`.demo`)."""

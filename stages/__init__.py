"""The stages of the pipeline, one registry per family (:mod:`scanreg.stages.registry`) and one contract per
family (:mod:`scanreg.stages.protocols`). Families with several implementations are packages (``data``,
``repair``, ``coarse``, ``icp``); the others are modules (``sampler``, ``salience``, ``descriptor``,
``matcher``)."""

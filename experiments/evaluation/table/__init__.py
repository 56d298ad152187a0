"""The denoising table's parts, shared by ``dss-denoise-table``
(:mod:`experiments.evaluation.denoise_table`), ``dss-sweep``, ``dss-real-bench`` and the outlier
study: :mod:`~experiments.evaluation.table.cases` (making and caching cases),
:mod:`~experiments.evaluation.table.runners` (running a method on a case, its record, reuse) and
:mod:`~experiments.evaluation.table.report` (summaries, the markdown table, the chart)."""

"""Benchmark suites: several scenes × skills, evaluated together and reported with intervals and provenance.

One job per module: :mod:`.rows` (a suite's rows and what a report says of each), :mod:`.baseline`
(speed-ups against a one-process run), :mod:`.policy_host` (a row's policy served once),
:mod:`.suite_run` (every row through an evaluator), :mod:`.provenance` (where and how it ran) and
:mod:`.report` (the report document, its progress lines and its Markdown table).
"""

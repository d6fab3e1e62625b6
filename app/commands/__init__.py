"""The `stairfit` subcommands, one module each (`predict`, `simulate`, `init`, `fit`, `measure`,
`demo`, `study`), every one with `add_parser(sub)` and `run(args)`; `stairfit.cli` imports only the
chosen command's module (issue 14), and nothing else imports one (tests/repository/test_layout.py):
a command parses its arguments, calls library functions (`stairfit.pipeline` for the fit) and
prints. Helpers private to the commands sit beside them (`_fit_options`, `_simulate_options`,
`_predict_checks`, `_predict_gloss`); a study's library is `stairfit.study`.

Nothing is imported here, so that `stairfit predict` does not import fit's module.
"""

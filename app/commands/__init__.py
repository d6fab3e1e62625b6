"""The `stairfit` subcommands, one module each (`predict`, `simulate`, `init`, `fit`, `measure`,
`demo`, `study`), every one with `add_parser(sub)` and `run(args)`; `stairfit.cli` imports only the
chosen command's module (issue 14). Helpers private to one command sit beside it (`_predict_checks`,
`_accuracy_check`, `_exclusions`, `_failed_previews`, `_layout`, `_study_task`, `study_report`).

Nothing is imported here, so that `stairfit predict` does not import fit's module.
"""

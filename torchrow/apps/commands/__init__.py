"""The commands of ``torchrow`` (:mod:`torchrow.apps.cli` builds the parser from them), one
module each: ``add_parser(subparsers)`` declares the command and its arguments,
``run(args) -> int`` runs it and returns the exit status. What several commands use lives in
:mod:`torchrow.apps.commands.shared`.
"""

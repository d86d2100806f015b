"""The command line's commands, one module per command, named after it ("attack train" -> ``attack_train``,
"victims export-onnx" -> ``victims_export_onnx``; :func:`robustbench3d.cli.command_module`).

Each module exposes ``add_arguments(parser)`` and ``run(args) -> int``, imports only the standard library at
module level, and never imports another command: what two commands share lives in the library below them
(the import contract ``commands-independent``). A new command is a module here plus its line in
:data:`robustbench3d.cli.COMMANDS`.
"""

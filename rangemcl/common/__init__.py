"""What every part of rangemcl uses and nothing of rangemcl's own: atomic writes and stable ``.npz`` bytes
(``atomic``), the output policy of the commands (``outdir``), worker pools that die with their parent
(``pool``), giving freed memory back (``heap``), YAML reading with clear errors (``yamlio``), checkpoints
without pickle (``checkpoint``) and the CLIs' shared helpers (``cliutil``). It imports numpy and the
standard library only (and ``rangemcl.errors``)."""

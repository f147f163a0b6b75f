"""The runtime every module stands on: the signed bus, shared time, the module loop and its
launcher, configuration and deployments. It imports protocol/ and nothing else of ours; brain/
and modules/ import rascal only from here. The rest of rascal/ is the tools on top (cli, run,
supervisor, recording, report, view...), which nothing below imports (tests/test_layers.py)."""

"""Imported first by the vision workers' fork server (see watchdog.worker_context).

Every process forked from the server re-runs the parent's main module as ``__mp_main__``; the
server preloads that module by name so the re-run finds its imports cached, and runpy then warns
that the module is already imported. The re-run is intended (its ``if __name__ == "__main__"``
guard keeps it inert), so that one warning is silenced here, in the server, whose filters every
worker inherits.
"""

import warnings

warnings.filterwarnings("ignore", message=r".*found in sys\.modules after import of package.*", category=RuntimeWarning)

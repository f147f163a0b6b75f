"""``python -m rascal.view --set port=P --set course=RDDF``: the viewer as a module process
(what ``rascal run --view`` supervises); ``rascal view`` is the friendlier front end."""

from rascal.runtime.launch import run_module
from rascal.view.module import Viewer

run_module(Viewer)

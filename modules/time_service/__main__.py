from modules.time_service import MODULE
from rascal.runtime.launch import run_module

run_module(MODULE)

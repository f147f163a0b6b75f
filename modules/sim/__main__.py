from modules.sim import MODULE
from rascal.runtime.launch import run_module

run_module(MODULE)

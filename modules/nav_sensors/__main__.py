from modules.nav_sensors import MODULE
from rascal.runtime.launch import run_module

run_module(MODULE)

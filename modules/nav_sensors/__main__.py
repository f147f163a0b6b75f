from modules.nav_sensors import MODULE
from rascal.launch import run_module

run_module(MODULE)

from modules.brain import MODULE
from rascal.launch import run_module

run_module(MODULE)

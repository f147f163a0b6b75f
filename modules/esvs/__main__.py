from modules.esvs import MODULE
from rascal.runtime.launch import run_module

# Guarded: the vision workers' fork server imports the main module of a process it serves.
if __name__ == "__main__":
    run_module(MODULE)

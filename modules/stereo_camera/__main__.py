from modules.stereo_camera import MODULE
from rascal.launch import run_module

run_module(MODULE)

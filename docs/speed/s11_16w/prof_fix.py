# profile_surface.py with the allocator settings gmmgp run applies (its own tree's)
import runpy, sys
from gmmgp_app import _memory
_memory.fix_mmap_threshold()
sys.argv = [sys.argv[1]] + sys.argv[2:]
runpy.run_path(sys.argv[0], run_name="__main__")

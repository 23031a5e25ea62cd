import sys, functools
from gmmgp_app import _memory
mm, trim = (int(v) for v in sys.argv.pop(1).split(":"))
_memory.fix_mmap_threshold = functools.partial(_memory.fix_mmap_threshold, mm, trim)
from gmmgp_app.cli import console_main
sys.argv[0] = "gmmgp"
console_main()

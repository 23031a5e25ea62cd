import sys
from gmmgp_app import _memory
mm, trim = (int(v) for v in sys.argv.pop(-1).split(":"))
print(_memory.fix_mmap_threshold(mm, trim))
sys.argv[2] = "nofixagain"
exec(open('/tmp/w16w/faults.py').read())

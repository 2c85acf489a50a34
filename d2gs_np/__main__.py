import sys

from d2gs_np.cli import main

sys.exit(main())

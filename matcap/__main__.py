import sys

from matcap.cli import main

sys.exit(main())

import sys

from eslam_core.cli import main

sys.exit(main())

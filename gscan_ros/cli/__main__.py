import sys

from gscan_ros.cli import main

sys.exit(main())

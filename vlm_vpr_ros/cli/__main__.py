"""``python -m vlm_vpr_ros.cli`` == ``vlm-vpr``."""

import sys

from vlm_vpr_ros.cli import main

sys.exit(main())

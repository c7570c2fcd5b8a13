import sys

from spine_client.cli import main

sys.exit(main())

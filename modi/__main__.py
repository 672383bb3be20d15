import sys

try:
    from modi.cli import main
except KeyboardInterrupt:  # Ctrl-C while Python is still importing: no traceback
    print("\nmodi: interrupted", file=sys.stderr, flush=True)
    sys.exit(130)

sys.exit(main())

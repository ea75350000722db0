"""``python -m ari_sfm``: the ari-sfm command line."""
from ari_sfm.cli import main

if __name__ == "__main__":
    main(prog_name="ari-sfm")

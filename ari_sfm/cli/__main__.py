"""``python -m ari_sfm.cli``: the command line (as ``python -m ari_sfm``), every command defined first."""
from ari_sfm.cli import main

if __name__ == "__main__":
    main()

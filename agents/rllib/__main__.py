import tyro

from agents.rllib.train import Args, main

if __name__ == "__main__":
    main(tyro.cli(Args))

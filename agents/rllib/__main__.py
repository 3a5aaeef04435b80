from agents.common.args import entry
from agents.rllib.train import Args, main

if __name__ == "__main__":
    entry(Args, "agents.rllib", main, recipes=False)

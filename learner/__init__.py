"""Networks, replay and one module per algorithm (MA-MeSN, MA-BoN, DIAL, IMS, DQN variants): the algorithms issue."""

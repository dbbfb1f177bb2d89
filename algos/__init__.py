"""The algorithm library: one file per algorithm (``idqn``, ``dqn_ser``, ``dial``, ``ims``, ``ma_mesn``, ``ma_bon``,
``ma_mesn_mm``, ``ma_bon_mm``, ``codbc``), the pieces they share (``nets``, ``replay``, ``algorithm``,
``listening``, ``memory``), hierarchical DQN around any of them (``hierarchy``), the name table (``registry``) and
checkpoints of an agent's state (``checkpoint``). No transport, no env stepping: actors and learners drive it."""

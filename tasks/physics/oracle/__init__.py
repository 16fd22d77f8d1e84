"""Library of the material oracle step (paper sec. 3.2): material schema, the offline table (data in
``materials.yaml``), description matching, oracle settings, the LLM client and the solver/artifact conversions."""

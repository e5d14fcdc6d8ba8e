"""The OIS camera simulator (models_spec/simulator.md), its device profiles and its photo renderer."""

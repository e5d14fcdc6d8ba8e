"""The OIS camera simulator (models_spec/simulator.md), its photo renderer and the render truth."""

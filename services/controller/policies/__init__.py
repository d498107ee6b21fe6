"""Landing policies: pure objects, heatmap and altitude in, command and status out."""

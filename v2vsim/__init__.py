"""v2vsim: multi-agent V2V cooperative-perception co-simulation."""

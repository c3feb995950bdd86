"""Cell orchestration: config, frames, locate/approach/jog, safety, jobs, hardware factory."""

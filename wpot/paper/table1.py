"""The paper's Table 1, which `wpot report` prints beside a run's own figures."""

__all__ = ["PAPER_TABLE1"]

#: paper Table 1: 1-NN success rates (%) on TOSCA8, one random training shape per class, 10,000 trials
PAPER_TABLE1 = {
    ("wks", "balanced"): 100.0,
    ("wks", "partial"): 98.6,
    ("ldsift", "balanced"): 83.3,
    ("ldsift", "partial"): 97.3,
}

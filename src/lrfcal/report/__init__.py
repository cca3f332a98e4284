"""What a person looks at: report.md (:mod:`.markdown`), the terminal summary, the PNG figures and the rerun viewer."""

"""What a person looks at: the terminal summary, the PNG figures and the rerun viewer."""

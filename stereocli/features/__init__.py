"""What a pair's images say before dense matching: sparse point matches, how well the rows are
aligned, and the disparity range the scene spans (for pairs without a known range)."""

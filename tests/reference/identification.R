# Reference values for facelab.analysis.identification.correct_model, computed with R's geepack.
# Run from this folder:  Rscript identification.R > identification_R.json
# Needs Debian r-base-core, r-cran-geepack.
suppressPackageStartupMessages(library(geepack))
d <- read.csv("identification.csv")
d$participant <- factor(d$participant)
d$condition <- factor(d$condition, levels = c("none", "gestures_only", "composite"))
d <- d[order(d$participant), ]

fit_json <- function(formula) {
  m <- geeglm(formula, id = participant, data = d, family = binomial,
              corstr = "exchangeable", scale.fix = FALSE)
  s <- summary(m)$coefficients
  fmt <- function(v) formatC(v, digits = 12, format = "g")
  terms <- sprintf('"%s": {"estimate": %s, "se": %s}', rownames(s), fmt(s[, "Estimate"]),
                   fmt(s[, "Std.err"]))
  sprintf('{"correlation": %s, "terms": {%s}}', fmt(m$geese$alpha[[1]]),
          paste(terms, collapse = ", "))
}
cat("{\n")
cat(sprintf('  "condition": %s,\n', fit_json(correct ~ condition)))
cat(sprintf('  "covariate": %s\n', fit_json(correct ~ condition + n_gesture)))
cat("}\n")

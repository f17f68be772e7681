# Reference values for facelab.analysis.psychometric, computed with R and psyphy
# (an implementation independent of facelab's). Run from this folder:
#   Rscript psychometric.R > psychometric_R.json
# Needs Debian r-base-core and r-cran-psyphy.
suppressPackageStartupMessages(library(psyphy))

afc <- read.csv("psychometric_2afc.csv")
yn <- read.csv("psychometric_yesno.csv")
out <- list()

# 2AFC, logistic, lapse fixed at 0: glm with psyphy's m-alternative logit link (gamma = 1/2)
m0 <- glm(cbind(k, n - k) ~ level, family = binomial(mafc.logit(2)), data = afc)
b <- coef(m0)
out$afc_logistic_lapse0 <- list(alpha = unname(-b[1] / b[2]), beta = unname(b[2]),
                                deviance = deviance(m0), loglik = as.numeric(logLik(m0)))

# 2AFC, logistic, lapse free in [0, 0.1]: the likelihood profiled over lambda with R's
# optimize(), each profile point a glm with psyphy's two-asymptote logit link
# P = 1/2 + (1 - 1/2 - lambda) * plogis(eta)
fit_lam <- function(lam) glm(cbind(k, n - k) ~ level, family = binomial(logit.2asym(0.5, lam)),
                             data = afc)
lam <- optimize(function(l) -as.numeric(logLik(fit_lam(l))), c(0, 0.1), tol = 1e-10)$minimum
m1 <- fit_lam(lam)
b <- coef(m1)
out$afc_logistic_lapse <- list(alpha = unname(-b[1] / b[2]), beta = unname(b[2]),
                               lapse = lam, deviance = deviance(m1))

# 2AFC, Weibull, lapse 0: F = 1 - exp(-exp(b0 + b1 log x)), so beta = b1, alpha = exp(-b0 / b1)
m2 <- glm(cbind(k, n - k) ~ log(level), family = binomial(mafc.cloglog(2)), data = afc)
b <- coef(m2)
out$afc_weibull_lapse0 <- list(alpha = unname(exp(-b[1] / b[2])), beta = unname(b[2]),
                               deviance = deviance(m2))

# yes/no (gamma = 0), logistic, lapse 0: the ordinary logistic regression
m3 <- glm(cbind(k, n - k) ~ level, family = binomial("logit"), data = yn)
b <- coef(m3)
out$yesno_logistic_lapse0 <- list(alpha = unname(-b[1] / b[2]), beta = unname(b[2]),
                                  deviance = deviance(m3))

fmt <- function(x) formatC(x, digits = 12, format = "g")
items <- sapply(names(out), function(nm) {
  vals <- out[[nm]]
  inner <- paste(sprintf('"%s": %s', names(vals), sapply(vals, fmt)), collapse = ", ")
  sprintf('  "%s": {%s}', nm, inner)
})
cat("{\n", paste(items, collapse = ",\n"), "\n}\n", sep = "")

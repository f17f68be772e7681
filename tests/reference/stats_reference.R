# Reference values for tests/test_stats.py, computed with R (Debian r-base-core 4.2.2,
# r-cran-afex, r-cran-lme4, r-cran-jsonlite). Regenerate with:
#   Rscript tests/reference/stats_reference.R   (from the repository root)
# Writes tests/reference/stats_reference.json and the raw data it used (plantgrowth.csv,
# chickwts.csv); rm3.csv and rm4.csv come from make_rm_fixtures.py.
suppressMessages({library(afex); library(lme4); library(jsonlite)})
here <- "tests/reference"
out <- list(generated_by = paste(R.version.string, "afex", packageVersion("afex"),
                                 "car", packageVersion("car"), "lme4", packageVersion("lme4")))

oneway <- function(df, dv, group) {
  f <- as.formula(paste(dv, "~", group))
  fit <- aov(f, data = df)
  tab <- summary(fit)[[1]]
  tk <- TukeyHSD(fit)[[group]]
  list(
    anova = list(df1 = tab$Df[1], df2 = tab$Df[2], f = tab$`F value`[1], p = tab$`Pr(>F)`[1],
                 eta_sq = tab$`Sum Sq`[1] / sum(tab$`Sum Sq`)),
    tukey = data.frame(pair = rownames(tk), diff = tk[, "diff"], ci_low = tk[, "lwr"],
                       ci_high = tk[, "upr"], p_adj = tk[, "p adj"], row.names = NULL)
  )
}

write.csv(PlantGrowth, file.path(here, "plantgrowth.csv"), row.names = FALSE)
write.csv(chickwts, file.path(here, "chickwts.csv"), row.names = FALSE)
out$plantgrowth <- oneway(PlantGrowth, "weight", "group")
out$chickwts <- oneway(chickwts, "weight", "feed")

within <- function(file) {
  d <- read.csv(file.path(here, file), stringsAsFactors = TRUE)
  d$condition <- factor(d$condition, levels = unique(as.character(d$condition)))
  m <- aggregate(rating ~ participant + condition, data = d, FUN = mean)
  m <- m[order(m$condition, m$participant), ]
  a <- aov_ez(id = "participant", dv = "rating", within = "condition", data = d,
              fun_aggregate = mean, anova_table = list(es = c("ges", "pes"), correction = "none"))
  s <- summary(a)
  uni <- s$univariate.tests
  adj <- s$pval.adjustments
  sph <- s$sphericity.tests
  res <- list(rm_anova = list(
    df1 = uni["condition", "num Df"], df2 = uni["condition", "den Df"],
    f = uni["condition", "F value"], p = uni["condition", "Pr(>F)"],
    w_mauchly = if (is.null(sph)) 1 else sph["condition", "Test statistic"],
    p_mauchly = if (is.null(sph)) 1 else sph["condition", "p-value"],
    eps_gg = if (is.null(adj)) 1 else adj["condition", "GG eps"],
    p_gg = if (is.null(adj)) uni["condition", "Pr(>F)"] else adj["condition", "Pr(>F[GG])"],
    eps_hf = if (is.null(adj)) 1 else adj["condition", "HF eps"],
    p_hf = if (is.null(adj)) uni["condition", "Pr(>F)"] else adj["condition", "Pr(>F[HF])"],
    eta_g_sq = a$anova_table["condition", "ges"], eta_p_sq = a$anova_table["condition", "pes"]))
  levs <- levels(m$condition)
  pairs <- list()
  for (i in 1:(length(levs) - 1)) for (j in (i + 1):length(levs)) {
    x <- m$rating[m$condition == levs[i]]; y <- m$rating[m$condition == levs[j]]
    tt <- t.test(x, y, paired = TRUE)
    pairs[[length(pairs) + 1]] <- data.frame(a = levs[i], b = levs[j], t = unname(tt$statistic),
      df = unname(tt$parameter), p_unc = tt$p.value, d_z = mean(x - y) / sd(x - y))
  }
  pairs <- do.call(rbind, pairs)
  for (method in c("holm", "bonferroni")) {
    pw <- pairwise.t.test(m$rating, m$condition, paired = TRUE, p.adjust.method = method)$p.value
    pairs[[paste0("p_", method)]] <- mapply(function(a, b) pw[b, a], pairs$a, pairs$b)
  }
  res$pairwise <- pairs
  fr <- friedman.test(rating ~ condition | participant, data = m)
  n <- length(unique(m$participant)); k <- length(levs)
  res$friedman <- list(chi2 = unname(fr$statistic), df = unname(fr$parameter), p = fr$p.value,
                       kendall_w = unname(fr$statistic) / (n * (k - 1)))
  if (max(table(d$participant, d$condition)) > 1) {
    fit <- lmer(rating ~ condition + (1 | participant) + (1 | participant:condition), data = d, REML = TRUE)
    res$lmer_f <- anova(fit)["condition", "F value"]
  }
  res
}
out$rm3 <- within("rm3.csv")
out$rm4 <- within("rm4.csv")
write(toJSON(out, digits = NA, auto_unbox = TRUE, pretty = TRUE), file.path(here, "stats_reference.json"))
cat("wrote", file.path(here, "stats_reference.json"), "\n")

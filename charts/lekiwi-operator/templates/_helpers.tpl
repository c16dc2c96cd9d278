{{- define "lekiwi.name" -}}
{{- default .Chart.Name .Values.nameOverride | trunc 63 | trimSuffix "-" -}}
{{- end -}}

{{- define "lekiwi.fullname" -}}
{{- if .Values.fullnameOverride -}}
{{- .Values.fullnameOverride | trunc 63 | trimSuffix "-" -}}
{{- else -}}
{{- $name := include "lekiwi.name" . -}}
{{- if contains $name .Release.Name -}}
{{- .Release.Name | trunc 63 | trimSuffix "-" -}}
{{- else -}}
{{- printf "%s-%s" .Release.Name $name | trunc 63 | trimSuffix "-" -}}
{{- end -}}
{{- end -}}
{{- end -}}

{{- define "lekiwi.selectorLabels" -}}
app.kubernetes.io/name: {{ include "lekiwi.name" . }}
app.kubernetes.io/instance: {{ .Release.Name }}
{{- end -}}

{{- define "lekiwi.labels" -}}
{{ include "lekiwi.selectorLabels" . }}
app.kubernetes.io/version: {{ .Chart.AppVersion | quote }}
app.kubernetes.io/managed-by: {{ .Release.Service }}
app.kubernetes.io/part-of: lekiwi
helm.sh/chart: {{ printf "%s-%s" .Chart.Name .Chart.Version | replace "+" "_" }}
{{- end -}}

{{- define "lekiwi.serviceAccountName" -}}
{{- if .Values.serviceAccount.create -}}
{{- default (include "lekiwi.fullname" .) .Values.serviceAccount.name -}}
{{- else -}}
{{- default "default" .Values.serviceAccount.name -}}
{{- end -}}
{{- end -}}

{{/* The claim holding events.db and blobs/, or nothing for an emptyDir. */}}
{{- define "lekiwi.claimName" -}}
{{- if .Values.persistence.existingClaim -}}
{{- .Values.persistence.existingClaim -}}
{{- else if .Values.persistence.enabled -}}
{{- printf "%s-data" (include "lekiwi.fullname" .) -}}
{{- end -}}
{{- end -}}

{{/* Whether the event store is the embedded SQLite file (a single writer). */}}
{{- define "lekiwi.sqlite" -}}
{{- if not .Values.store.postgres.existingSecret -}}true{{- end -}}
{{- end -}}

{{/*
Refuses topologies that lose data or split the store, with a message that says what to change.
The schema checks each value; these rules relate several.
*/}}
{{- define "lekiwi.validate" -}}
{{- $v := .Values -}}
{{- if gt (int $v.replicaCount) 1 -}}
{{- if include "lekiwi.sqlite" . -}}
{{- fail (printf "replicaCount=%d needs store.postgres.existingSecret: the SQLite event store has a single writer. Use replicaCount=1, or PostgreSQL plus a ReadWriteMany blob volume (persistence.accessModes=[ReadWriteMany] or a ReadWriteMany persistence.existingClaim)." (int $v.replicaCount)) -}}
{{- end -}}
{{- if and (not $v.persistence.existingClaim) (not $v.persistence.enabled) -}}
{{- fail (printf "replicaCount=%d with persistence.enabled=false gives every replica its own emptyDir blob store: a release pushed to one replica is missing on the others. Enable persistence with accessModes=[ReadWriteMany] or set persistence.existingClaim to a ReadWriteMany claim." (int $v.replicaCount)) -}}
{{- end -}}
{{- if and (not $v.persistence.existingClaim) (not (has "ReadWriteMany" $v.persistence.accessModes)) -}}
{{- fail (printf "replicaCount=%d needs persistence.accessModes to include ReadWriteMany: every replica's gateway serves the release blob store from the same volume (a ReadWriteOnce volume cannot be mounted by pods on several nodes)." (int $v.replicaCount)) -}}
{{- end -}}
{{- end -}}
{{- if and $v.podDisruptionBudget.enabled (kindIs "invalid" $v.podDisruptionBudget.minAvailable) (kindIs "invalid" $v.podDisruptionBudget.maxUnavailable) -}}
{{- fail "podDisruptionBudget: set minAvailable or maxUnavailable (or enabled=false)" -}}
{{- end -}}
{{- end -}}

{{/* Where the gateway's certificate comes from: `existing` (a Secret the user made),
`certManager` (a Certificate the chart renders), `generated` (a CA the chart makes), or nothing
for plain text (gateway.tls.enabled=false) and for role=controller (no gateway). */}}
{{- define "lekiwi.tlsMode" -}}
{{- $tls := .Values.gateway.tls -}}
{{- if and $tls.enabled (ne .Values.operator.role "controller") -}}
{{- if or $tls.existingSecret $tls.secretName -}}existing
{{- else if $tls.certManager.enabled -}}certManager
{{- else -}}generated
{{- end -}}
{{- end -}}
{{- end -}}

{{/* The TLS Secret the gateway serves with, or nothing for plain text. */}}
{{- define "lekiwi.tlsSecret" -}}
{{- $mode := include "lekiwi.tlsMode" . -}}
{{- $fullname := include "lekiwi.fullname" . -}}
{{- if eq $mode "existing" -}}
{{- .Values.gateway.tls.existingSecret | default .Values.gateway.tls.secretName -}}
{{- else if eq $mode "certManager" -}}
{{- printf "%s-gateway-cert" $fullname -}}
{{- else if eq $mode "generated" -}}
{{- printf "%s-gateway-tls" $fullname -}}
{{- end -}}
{{- end -}}

{{/* Whether the chart makes the gateway's CA and certificate itself. */}}
{{- define "lekiwi.tlsGenerated" -}}
{{- if eq (include "lekiwi.tlsMode" .) "generated" -}}true{{- end -}}
{{- end -}}

{{/* The DNS names the gateway's certificate carries: the gateway and API Services' names in
the cluster, localhost and gateway.tls.extraDnsNames (a JSON list). */}}
{{- define "lekiwi.tlsDnsNames" -}}
{{- $fullname := include "lekiwi.fullname" . -}}
{{- $ns := .Release.Namespace -}}
{{- $names := list -}}
{{- range $svc := list (printf "%s-gateway" $fullname) (printf "%s-api" $fullname) -}}
{{- $names = concat $names (list $svc (printf "%s.%s" $svc $ns) (printf "%s.%s.svc" $svc $ns) (printf "%s.%s.svc.cluster.local" $svc $ns)) -}}
{{- end -}}
{{- concat $names (list "localhost") .Values.gateway.tls.extraDnsNames | toJson -}}
{{- end -}}

{{/* Relations between TLS values the schema cannot express. */}}
{{- define "lekiwi.validateTls" -}}
{{- $tls := .Values.gateway.tls -}}
{{- if and $tls.enabled $tls.certManager.enabled -}}
{{- if or $tls.existingSecret $tls.secretName -}}
{{- fail "gateway.tls: set either existingSecret (a Secret you keep) or certManager.enabled (cert-manager issues it), not both" -}}
{{- end -}}
{{- if not $tls.certManager.issuerRef.name -}}
{{- fail "gateway.tls.certManager.enabled needs gateway.tls.certManager.issuerRef.name: the Issuer or ClusterIssuer that signs the gateway's certificate" -}}
{{- end -}}
{{- end -}}
{{- end -}}
